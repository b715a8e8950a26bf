"""A private CPU Vulkan driver for SAPIEN (ManiSkill3), without touching the system.

SAPIEN creates a Vulkan instance even for state-only tasks (building a cube makes a
render material), and Debian 12's lavapipe (Mesa 22.3) is refused with
`ErrorIncompatibleDriver`. Mesa 25's lavapipe from bookworm-backports works. Installing
it system-wide could break other software, so `install()` downloads its packages from
Debian's archive (a package registry, like PyPI), checks each against a pinned SHA-256,
unpacks them into a private folder, and writes an ICD file that names the driver by
absolute path. `activate()` then makes this process use it: it loads the private
`libdrm`/`libvulkan` by absolute path before SAPIEN does (the dynamic linker reuses a
library already loaded under the same soname; `LD_LIBRARY_PATH` is read only when a
process starts, so setting it here would do nothing) and points `VK_ICD_FILENAMES` at
the ICD file, which the Vulkan loader reads when the instance is created.

    python -m adapters.vulkan install     # once per machine (tox's test env runs it)
    python -m adapters.vulkan check       # does SAPIEN get a Vulkan device now?

A machine with a working Vulkan driver of its own (a GPU, a newer Mesa) needs none of
this: set `DVLA_VULKAN=system`, or simply do not install it. What a run used is in its
manifest (`suite.provenance.vulkan_driver`).
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import io
import json
import lzma
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ARCHIVE = "http://deb.debian.org/debian"
DRIVER = "lavapipe, Mesa 25.0.7 (Debian bookworm-backports)"


@dataclass(frozen=True)
class Deb:
    package: str
    version: str
    path: str  # under ARCHIVE
    sha256: str
    index: str  # the Packages index that lists it (for a fallback when the pin is gone)


# What lavapipe needs beyond a bookworm base image: the driver, the newer libdrm it links
# against, and the Vulkan loader. Versions and hashes as Debian's Packages indexes list them.
PINNED = (
    Deb(
        "mesa-vulkan-drivers",
        "25.0.7-2~bpo12+1",
        "pool/main/m/mesa/mesa-vulkan-drivers_25.0.7-2~bpo12+1_amd64.deb",
        "3899f1800424c60a05df5d6913076a526ca8fdbabec43672cd397563d1ca3263",
        "dists/bookworm-backports/main/binary-amd64/Packages.xz",
    ),
    Deb(
        "libdrm2",
        "2.4.123-1~bpo12+1",
        "pool/main/libd/libdrm/libdrm2_2.4.123-1~bpo12+1_amd64.deb",
        "9cc2f341964286295124a32d3625edb76730500625e54a1e682761f883064d7b",
        "dists/bookworm-backports/main/binary-amd64/Packages.xz",
    ),
    Deb(
        "libdrm-amdgpu1",
        "2.4.123-1~bpo12+1",
        "pool/main/libd/libdrm/libdrm-amdgpu1_2.4.123-1~bpo12+1_amd64.deb",
        "334e2ae389af0e9cb607c2ccfbbf7ae9feb34131ff998550baeffeeae6cda296",
        "dists/bookworm-backports/main/binary-amd64/Packages.xz",
    ),
    Deb(
        "libvulkan1",
        "1.3.239.0-1",
        "pool/main/v/vulkan-loader/libvulkan1_1.3.239.0-1_amd64.deb",
        "622f28b807ba55a1f5ad1622ff83aa2c5b11fedbec074850e04c10a8f28b43d3",
        "dists/bookworm/main/binary-amd64/Packages.xz",
    ),
)
LIB = "usr/lib/x86_64-linux-gnu"
PRELOAD = ("libdrm.so.2", "libvulkan.so.1")  # in this order: the loader after what lvp links
ICD = "lvp_icd.json"
RECORD = "installed.json"


class VulkanSetupError(RuntimeError):
    """The private driver cannot be installed or used; the message says what to do."""


def home() -> Path:
    """Where the private driver lives: $DVLA_VULKAN_DIR, else the user's cache folder."""
    if os.environ.get("DVLA_VULKAN_DIR"):
        return Path(os.environ["DVLA_VULKAN_DIR"])
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "dvla-harness" / "vulkan"


def installed() -> dict | None:
    """The install record ({driver, packages, icd}), or None when there is none."""
    try:
        return json.loads((home() / RECORD).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def describe() -> str:
    """The Vulkan driver this process would give SAPIEN, for manifests (no import)."""
    if os.environ.get("DVLA_VULKAN") == "system":
        return f"system (DVLA_VULKAN=system; VK_ICD_FILENAMES={os.environ.get('VK_ICD_FILENAMES', 'unset')})"
    record = installed()
    if record is None:
        return "system (no private driver installed: python -m adapters.vulkan install)"
    packages = ", ".join(f"{p} {v}" for p, v in record["packages"].items())
    return f"{record['driver']}, private ({packages})"  # no path: it differs between machines


_ACTIVE: list[str] = []


def activate() -> str:
    """Make this process use the private driver (if installed and not opted out); call
    before SAPIEN is imported. Returns describe(). Idempotent."""
    if _ACTIVE or os.environ.get("DVLA_VULKAN") == "system":
        return describe()
    record = installed()
    if record is None:
        return describe()
    lib = home() / LIB
    try:
        for name in PRELOAD:
            ctypes.CDLL(str(lib / name), mode=ctypes.RTLD_GLOBAL)
    except OSError as exc:
        raise VulkanSetupError(
            f"the private Vulkan driver at {home()} does not load ({exc}); reinstall it with "
            "`python -m adapters.vulkan install --force`, or use the system's with DVLA_VULKAN=system"
        ) from None
    os.environ["VK_ICD_FILENAMES"] = str(home() / ICD)
    _ACTIVE.append(str(home()))
    return describe()


# --- installing ---------------------------------------------------------------------


def _fetch(url: str) -> bytes:
    try:
        with urllib.request.urlopen(url, timeout=120) as response:
            return response.read()
    except urllib.error.HTTPError:
        raise  # the archive answered: _download handles a file that has moved
    except (urllib.error.URLError, TimeoutError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise VulkanSetupError(
            f"cannot download the private Vulkan driver for ManiSkill3: {url} is unreachable ({reason}; "
            "is this machine offline?); nothing installed: run `python -m adapters.vulkan install` "
            "when online, or use the system's driver with DVLA_VULKAN=system"
        ) from None


def _current(deb: Deb) -> Deb:
    """The version the archive's index lists now, when the pinned file is gone (backports
    keep only their newest build); its hash comes from that index."""
    index = lzma.decompress(_fetch(f"{ARCHIVE}/{deb.index}")).decode()
    for stanza in index.split("\n\n"):
        fields = dict(line.split(": ", 1) for line in stanza.splitlines() if ": " in line)
        if fields.get("Package") == deb.package:
            return Deb(deb.package, fields["Version"], fields["Filename"], fields["SHA256"], deb.index)
    raise VulkanSetupError(f"{deb.package} is no longer in {ARCHIVE}/{deb.index}")


def _download(deb: Deb, say: Callable[[str], None]) -> tuple[Deb, bytes]:
    try:
        data = _fetch(f"{ARCHIVE}/{deb.path}")
    except urllib.error.HTTPError as exc:
        if exc.code != 404:
            raise
        newer = _current(deb)
        say(
            f"  {deb.package} {deb.version} is gone from the archive; using {newer.version} (hash from its index)"
        )
        deb, data = newer, _fetch(f"{ARCHIVE}/{newer.path}")
    digest = hashlib.sha256(data).hexdigest()
    if digest != deb.sha256:
        raise VulkanSetupError(
            f"{deb.path}: sha256 {digest} is not the expected {deb.sha256}; nothing installed"
        )
    return deb, data


def _unpack_deb(data: bytes, into: Path) -> None:
    """A .deb is an `ar` archive whose data.tar.* member holds the files."""
    if not data.startswith(b"!<arch>\n"):
        raise VulkanSetupError("not a .deb (no ar header)")
    pos = 8
    while pos + 60 <= len(data):
        header = data[pos : pos + 60]
        name = header[:16].decode().strip().rstrip("/")
        size = int(header[48:58].decode().strip())
        body = data[pos + 60 : pos + 60 + size]
        if name.startswith("data.tar"):
            with tarfile.open(fileobj=io.BytesIO(body), mode="r:*") as tar:
                tar.extractall(into, filter="data")
            return
        pos += 60 + size + (size % 2)
    raise VulkanSetupError("a .deb without a data.tar member")


def install(force: bool = False, say: Callable[[str], None] = print) -> Path:
    """Download, verify and unpack the driver into home(); atomic (a half-done install
    leaves nothing behind). Returns home()."""
    target = home()
    if installed() is not None and not force:
        say(f"vulkan: {describe()} (already installed)")
        return target
    if not sys.platform.startswith("linux") or os.uname().machine != "x86_64":
        raise VulkanSetupError(
            "the private lavapipe driver is built for x86_64 Linux (Debian 12); on this machine "
            "use its own Vulkan driver (DVLA_VULKAN=system)"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".vulkan-", dir=target.parent))
    try:
        versions = {}
        for deb in PINNED:
            say(f"vulkan: fetching {deb.package} {deb.version}")
            got, data = _download(deb, say)
            _unpack_deb(data, staging)
            versions[got.package] = got.version
        icd = json.loads((staging / "usr/share/vulkan/icd.d/lvp_icd.json").read_text())
        icd["ICD"]["library_path"] = str(target / LIB / "libvulkan_lvp.so")
        (staging / ICD).write_text(json.dumps(icd, indent=2) + "\n")
        driver = DRIVER.replace("25.0.7", versions["mesa-vulkan-drivers"].split("-")[0])
        (staging / RECORD).write_text(json.dumps({"driver": driver, "packages": versions}, indent=2) + "\n")
        if target.exists():
            shutil.rmtree(target)
        staging.rename(target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    say(f"vulkan: installed {describe()} in {target}")
    return target


CHECK = (
    "import adapters.vulkan as v; v.activate(); import sapien; sapien.render.RenderSystem('cpu'); print('ok')"
)


def check() -> tuple[bool, str]:
    """Whether SAPIEN gets a Vulkan device in a fresh process (a failed driver can abort
    a process, so not in this one), and what it said."""
    root = Path(__file__).resolve().parent.parent
    env = os.environ | {
        "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))
    }
    out = subprocess.run(
        [sys.executable, "-c", CHECK], capture_output=True, text=True, env=env, timeout=300, check=False
    )
    ok = out.returncode == 0 and out.stdout.strip().endswith("ok")
    if ok:
        return True, describe()
    said = (out.stdout + out.stderr).strip().splitlines()
    return False, said[-1] if said else f"the check process exited {out.returncode} without a message"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m adapters.vulkan",
        description="A private CPU Vulkan driver (Mesa 25 lavapipe) for ManiSkill3/SAPIEN; no system change.",
    )
    parser.add_argument("action", choices=("install", "check", "where"))
    parser.add_argument("--force", action="store_true", help="reinstall even if installed")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)

    def say(text: str) -> None:
        if not args.quiet:
            print(text)

    try:
        if args.action == "install":
            install(args.force, say)
        elif args.action == "where":
            print(describe())
        else:
            ok, message = check()
            print(("ok: " if ok else "no Vulkan device for SAPIEN: ") + message)
            return 0 if ok else 1
    except (VulkanSetupError, OSError, urllib.error.URLError) as exc:
        print(f"vulkan: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
