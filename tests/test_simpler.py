"""The SimplerEnv-like ManiSkill3 suites: listing without the simulator, bad names, the
private Vulkan driver's installer (on hand-made packages: hash checks, atomicity), and
the real simulator: it builds and steps, a spec always starts from the same layout, the
state vector says where positions are, the scripted expert solves a task through the
CLI, and the manifest names the Vulkan driver."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile

import numpy as np
import pytest

from adapters import simpler, vulkan
from adapters.registry import UnknownSuiteError, list_suites, load_suite

needs_maniskill = pytest.mark.skipif(not simpler._installed(), reason="needs the maniskill extra")


def test_suites_list_and_load_without_the_simulator():
    names = {s.name for s in list_suites()}
    assert {"simpler/all", "simpler/pick_cube", "simpler/stack_cube"} <= names
    suite = load_suite("simpler/all")
    assert [t.name for t in suite.tasks] == list(simpler.TASKS)
    assert len(simpler.TASKS) >= 5 and suite.extra == "maniskill"
    task = suite.tasks[0]
    assert len(task.episodes) == simpler.EPISODES_PER_TASK and task.max_steps == 50
    assert "vulkan_driver" in suite.provenance
    seeds = {e.seed for t in suite.tasks for e in t.episodes}
    train = {e.seed for t in load_suite("simpler/all", "train").tasks for e in t.episodes}
    assert len(seeds) == len(simpler.TASKS) * simpler.EPISODES_PER_TASK and not seeds & train


def test_an_unknown_task_names_the_valid_ones(cli, tmp_path):
    with pytest.raises(UnknownSuiteError, match="simpler/pick_cube"):
        load_suite("simpler/open_drawer")
    code, _, err = cli("run", "--suite", "simpler/nope", "--policy", "random", "--out", str(tmp_path / "r"))
    assert code == 2 and "simpler/all" in err and not (tmp_path / "r").exists()


def test_the_state_layout_names_every_position():
    task = simpler.TASKS["stack_cube"]
    layout = {name: (a, b) for name, a, b in simpler.state_layout(task)}
    assert layout["tcp_pos"] == (0, 3) and layout["cubeA_pose"][1] - layout["cubeA_pose"][0] == 7
    assert simpler.state_positions(task) == (0, layout["cubeA_pose"][0], layout["cubeB_pose"][0])


# --- the private Vulkan driver ---------------------------------------------------------


def _deb(files: dict[str, bytes]) -> bytes:
    """A minimal .deb: an ar archive with a data.tar.xz member."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:xz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    members = [("debian-binary", b"2.0\n"), ("data.tar.xz", buf.getvalue())]
    out = b"!<arch>\n"
    for name, body in members:
        out += f"{name + '/':<16}{0:<12}{0:<6}{0:<6}{'100644':<8}{len(body):<10}`\n".encode() + body
        out += b"\n" if len(body) % 2 else b""
    return out


@pytest.fixture
def archive(monkeypatch, tmp_path):
    """Hand-made packages served in place of Debian's archive; returns the served files."""
    icd = json.dumps({"ICD": {"library_path": "libvulkan_lvp.so", "api_version": "1.4"}}).encode()
    served = {
        "mesa": _deb({"./usr/share/vulkan/icd.d/lvp_icd.json": icd, "./usr/lib/x86_64-linux-gnu/x.so": b"x"}),
        "drm": _deb({"./usr/lib/x86_64-linux-gnu/libdrm.so.2": b"d"}),
    }
    pinned = (
        vulkan.Deb(
            "mesa-vulkan-drivers", "25.1.0-1", "mesa", hashlib.sha256(served["mesa"]).hexdigest(), "i"
        ),
        vulkan.Deb("libdrm2", "2.4.123-1", "drm", hashlib.sha256(served["drm"]).hexdigest(), "i"),
    )
    monkeypatch.setattr(vulkan, "PINNED", pinned)
    monkeypatch.setattr(vulkan, "_fetch", lambda url: served[url.rsplit("/", 1)[-1]])
    monkeypatch.setenv("DVLA_VULKAN_DIR", str(tmp_path / "vk"))
    monkeypatch.delenv("DVLA_VULKAN", raising=False)
    return served


def test_install_unpacks_verified_packages_and_points_the_icd_at_them(archive, tmp_path):
    home = vulkan.install(say=lambda _: None)
    assert home == tmp_path / "vk" and (home / "usr/lib/x86_64-linux-gnu/libdrm.so.2").read_bytes() == b"d"
    icd = json.loads((home / vulkan.ICD).read_text())
    assert icd["ICD"]["library_path"] == str(home / "usr/lib/x86_64-linux-gnu/libvulkan_lvp.so")
    described = vulkan.describe()
    assert "Mesa 25.1.0" in described and "libdrm2 2.4.123-1" in described and "private" in described
    assert vulkan.install(say=lambda _: None) == home  # already there: nothing fetched again


def test_a_package_with_the_wrong_hash_installs_nothing(archive, monkeypatch, tmp_path):
    archive["drm"] = archive["drm"] + b"tampered"
    with pytest.raises(vulkan.VulkanSetupError, match="sha256"):
        vulkan.install(say=lambda _: None)
    assert vulkan.installed() is None
    assert not [p for p in (tmp_path).iterdir() if p.name.startswith(".vulkan-")]  # no staging left
    assert "no private driver installed: python -m adapters.vulkan install" in vulkan.describe()


def test_a_pinned_package_gone_from_the_archive_falls_back_to_the_index(archive, monkeypatch):
    import lzma
    import urllib.error

    newer = archive["drm"]
    index = lzma.compress(
        f"Package: libdrm2\nVersion: 2.4.124-1\nFilename: drm-new\nSHA256: {hashlib.sha256(newer).hexdigest()}\n".encode()
    )
    files = dict(archive) | {"drm-new": newer, "i": index}
    del files["drm"]

    def fetch(url: str) -> bytes:
        name = url.rsplit("/", 1)[-1]
        if name not in files:
            raise urllib.error.HTTPError(url, 404, "gone", None, None)  # type: ignore[arg-type]
        return files[name]

    monkeypatch.setattr(vulkan, "_fetch", fetch)
    said: list[str] = []
    vulkan.install(say=said.append)
    assert any("is gone from the archive; using 2.4.124-1" in s for s in said)
    assert vulkan.installed()["packages"]["libdrm2"] == "2.4.124-1"


def test_system_driver_opt_out(monkeypatch):
    monkeypatch.setenv("DVLA_VULKAN", "system")
    assert vulkan.describe().startswith("system (DVLA_VULKAN=system")


# --- the real simulator ----------------------------------------------------------------


@needs_maniskill
def test_maniskill_builds_steps_and_a_spec_always_starts_the_same():
    suite = load_suite("simpler/all")
    for task in suite.tasks:
        env = suite.make_env(task)
        try:
            first, info = env.reset(options={"episode": task.episodes[0]})
            assert first.shape == env.observation_space.shape and first.dtype == np.float32
            assert info == {"success": False}
            obs, _, _, _, info = env.step(np.zeros(7, dtype=np.float32))
            assert isinstance(info["success"], bool) and np.isfinite(obs).all()
            other, _ = env.reset(options={"episode": task.episodes[1]})
            again, _ = env.reset(options={"episode": task.episodes[0]})
            np.testing.assert_array_equal(first, again)
            assert not np.array_equal(first, other)  # another seed, another layout
            tcp = first[0:3]
            for start in env.state_positions[1:]:  # objects and goals lie on or above the table
                assert first[start + 2] > -0.01 and np.linalg.norm(first[start : start + 2] - tcp[:2]) < 1.0
        finally:
            env.close()


@needs_maniskill
def test_the_expert_solves_its_tasks_and_the_manifest_names_the_vulkan_driver(cli, tmp_path):
    import pandas as pd

    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "simpler/all", "--policy", "maniskill_scripted", "--episodes-per-task", "2",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet")
    assert len(rows) == 2 * len(simpler.TASKS) and rows["success"].all()  # 24/24 per task measured
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"]["provenance"]["vulkan_driver"] == vulkan.describe()
    assert set(manifest["suite"]["simulator_packages"]) == {"mani_skill", "sapien"}
