"""What the test command installs from outside PyPI (Debian's chromium with apt-get, a
Vulkan driver from Debian's archive) fails with one line naming what is missing when
the machine is offline, instead of apt's or urllib's screens of output."""

from __future__ import annotations

import os
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from adapters import vulkan

SCRIPT = Path(__file__).resolve().parent / "ensure_chromium.sh"


def test_the_vulkan_install_offline_is_one_line_and_installs_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DVLA_VULKAN_DIR", str(tmp_path / "vulkan"))

    def offline(url, timeout=None):
        raise urllib.error.URLError(OSError(-3, "Temporary failure in name resolution"))

    monkeypatch.setattr(urllib.request, "urlopen", offline)
    assert vulkan.main(["install", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "cannot download the private Vulkan driver for ManiSkill3" in err and "offline" in err
    assert "Temporary failure in name resolution" in err and "DVLA_VULKAN=system" in err
    assert [p.name for p in tmp_path.iterdir()] == []  # no staging folder, no half install


@pytest.mark.skipif(os.geteuid() != 0, reason="the script installs only as root")
def test_chromium_offline_is_one_line_naming_what_is_missing(tmp_path):
    stub = tmp_path / "bin"
    stub.mkdir()
    apt = stub / "apt-get"  # what apt-get says on a machine without a network
    apt.write_text(
        '#!/bin/sh\necho "W: Failed to fetch http://deb.debian.org/debian/dists/bookworm/InRelease"\n'
        "echo \"E: Temporary failure resolving 'deb.debian.org'\" >&2\nexit 100\n"
    )
    apt.chmod(0o755)
    missing = tmp_path / "chromium"
    env = os.environ | {"PATH": f"{stub}:{os.environ['PATH']}", "DVLA_CHROMIUM": str(missing)}
    out = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 1 and out.stdout == ""
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith(f"ensure_chromium: {missing} is missing and apt-get could not install")
    assert "offline" in line and "Temporary failure resolving 'deb.debian.org'" in line
