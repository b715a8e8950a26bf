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
            assert info == {"success": False, "variant": "canonical"}
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
def test_a_video_frame_is_the_tasks_render_camera_and_steps_nothing():
    suite = load_suite("simpler/all")
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        env.reset(options={"episode": task.episodes[0]})
        frame = env.video_frame()
        assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
        assert frame.std() > 10  # a rendered scene, not a blank frame
        state = env.env.unwrapped.get_state_dict()
        np.testing.assert_array_equal(frame, env.video_frame())
        after = env.env.unwrapped.get_state_dict()
        for key in ("actors", "articulations"):  # a capture moves nothing in the scene
            for name, value in state[key].items():
                np.testing.assert_array_equal(np.asarray(value), np.asarray(after[key][name]))
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


# --- variants ----------------------------------------------------------------------------


def test_variant_selection_names_and_episode_indices():
    from adapters import simpler_variants as sv

    every = sv.all_variants()
    assert {v.axis for v in every} >= {
        "lighting",
        "table",
        "camera",
        "distractors",
        "friction",
        "mass",
        "background",
    }
    # an axis added later goes at the end, so every earlier episode index stays as it was
    assert simpler.variant_number(sv.Variant("mass", "heavy")) == 15
    assert simpler.variant_number(sv.Variant("background", "dark")) == 16
    assert sv.parse("canonical") == (sv.CANONICAL_VARIANT,)
    assert sv.parse("all") == (sv.CANONICAL_VARIANT, *every)
    some = sv.parse("camera.left+lighting")  # file order, the canonical first, each once
    assert [v.label for v in some] == [
        "canonical",
        "lighting=dim",
        "lighting=bright",
        "lighting=warm",
        "camera=left",
    ]
    assert sv.name(some) == "lighting+camera.left" and sv.name(sv.parse("all")) == "all"
    suite = load_suite("simpler/pick_cube:variants=lighting.dim+mass")
    assert suite.name == "simpler/pick_cube:variants=lighting.dim+mass"
    specs = suite.tasks[0].episodes
    assert len(specs) == 4 * simpler.EPISODES_PER_TASK
    by_label = {sv.label(s.variant) for s in specs}
    assert by_label == {"canonical", "lighting=dim", "mass=light", "mass=heavy"}
    # an episode's index is the same whichever variants a run selects; its layout is the canonical one's
    alone = load_suite("simpler/pick_cube:variants=mass.heavy").tasks[0].episodes
    heavy = [s for s in specs if s.variant["level"] == "heavy"]
    assert [(s.index, s.seed) for s in heavy] == [
        (s.index, s.seed) for s in alone if s.variant["level"] == "heavy"
    ]
    assert [s.seed for s in heavy] == [s.seed for s in specs[: simpler.EPISODES_PER_TASK]]


@pytest.mark.parametrize(
    ("suite", "needle"),
    [
        ("simpler/pick_cube:variants=fog", "unknown variant axis 'fog'"),
        ("simpler/pick_cube:variants=lighting.neon", "its levels: lighting.dim, lighting.bright"),
        ("simpler/pick_cube:colour=red", "valid options: variants="),
        ("simpler/pick_cube:image_size=64", "needs obs=images"),
    ],
)
def test_bad_variants_exit_2_naming_the_valid_ones(cli, tmp_path, suite, needle):
    out = tmp_path / "r"
    code, _, err = cli("run", "--suite", suite, "--policy", "random", "--out", str(out))
    assert code == 2 and needle in err and not out.exists()


def test_the_variants_flag_is_the_suite_option(cli, tmp_path):
    from harness.config import with_variants
    from harness.errors import UsageError

    assert with_variants("simpler/all", "all") == "simpler/all:variants=all"
    assert (
        with_variants("simpler/all:variants=camera,obs=images", "mass")
        == "simpler/all:variants=mass,obs=images"
    )
    with pytest.raises(UsageError, match="applies to the simpler/ suites"):
        with_variants("metaworld/mt10", "all")
    code, _, err = cli("run", "--suite", "metaworld/mt10", "--variants", "all", "--out", str(tmp_path / "r"))
    assert code == 2 and "--variants applies to the simpler/ suites" in err


def test_simplerenv_selects_each_tasks_own_set():
    """`variants=simplerenv`: pick_cube runs coke can's 9 settings, push_cube move near's 8;
    the name records the selection, and a level every set holds adds nothing to it."""
    from adapters import simpler_variants as sv

    suite = load_suite("simpler/all:variants=simplerenv")
    assert suite.name == "simpler/all:variants=simplerenv"
    labels = {
        t.name: [sv.label(s.variant) for s in t.episodes[:: simpler.EPISODES_PER_TASK]] for t in suite.tasks
    }
    assert labels["pick_cube"] == [v.label for v in sv.parse("canonical+lighting.dim+lighting.bright")] + [
        "table=dark", "table=white", "distractors=one", "distractors=three", "background=dark", "background=sand",
    ]  # fmt: skip
    assert len(labels["push_cube"]) == 8 and "distractors=three" not in labels["push_cube"]
    # the same settings keep their episode indices in every selection
    alone = load_suite("simpler/push_cube:variants=distractors.one").tasks[0].episodes
    push = next(t for t in suite.tasks if t.name == "push_cube").episodes
    one = [(s.index, s.seed) for s in push if sv.label(s.variant) == "distractors=one"]
    assert one == [(s.index, s.seed) for s in alone if sv.label(s.variant) == "distractors=one"]
    assert (
        load_suite("simpler/all:variants=lighting.dim+simplerenv").name == "simpler/all:variants=simplerenv"
    )
    extra = load_suite("simpler/push_cube:variants=simplerenv+lighting+camera.left")
    assert extra.name == "simpler/push_cube:variants=simplerenv+lighting.warm+camera.left"
    assert len(extra.tasks[0].episodes) == 10 * simpler.EPISODES_PER_TASK
    assert sv.simplerenv_sets()[1].keys() == simpler.TASKS.keys()  # every task follows a set


def test_a_sets_file_naming_a_level_outside_simplerenvs_axes_is_refused(tmp_path):
    from adapters import simpler_variants as sv
    from adapters.registry import SuiteDataError

    bad = tmp_path / "s.toml"
    body = '[sets.x]\nsimplerenv_task = "t"\nwhat = "w"\nvariants = ["{}"]\n[tasks]\npick_cube = "x"\n'
    bad.write_text(body.format("camera.left"))
    with pytest.raises(SuiteDataError, match=r"'camera\.left' is not a level of SimplerEnv's axes"):
        sv.simplerenv_sets(bad)
    bad.write_text(body.format("lighting.neon"))
    with pytest.raises(SuiteDataError, match=r"'lighting\.neon' is not a level"):
        sv.simplerenv_sets(bad)
    bad.write_text(body.format("lighting.dim").replace('pick_cube = "x"', 'pick_cube = "y"'))
    with pytest.raises(SuiteDataError, match="unknown sets \\['y'\\]"):
        sv.simplerenv_sets(bad)


def test_a_variants_data_file_with_a_bad_level_is_refused(tmp_path):
    from adapters import simpler_variants as sv
    from adapters.registry import SuiteDataError

    bad = tmp_path / "v.toml"
    bad.write_text('[camera]\nkind = "visual"\nlevels.up = { offset = [0.0, 0.1] }\n')
    with pytest.raises(SuiteDataError, match="offset must be 3 numbers"):
        sv.axes(bad)
    bad.write_text('[fog]\nkind = "visual"\nlevels.thick = { density = 1.0 }\n')
    with pytest.raises(SuiteDataError, match="unknown axis \\[fog\\]"):
        sv.axes(bad)
    bad.write_text('[distractors]\nkind = "visual"\nlevels.one = { colors = [[0.9, 0.8]] }\n')
    with pytest.raises(SuiteDataError, match="colors must be a list of \\[r, g, b, a\\]"):
        sv.axes(bad)
    bad.write_text(
        '[distractors]\nkind = "visual"\nlevels.one = { positions = [[0.0, 0.19]], colors = [] }\n'
    )
    with pytest.raises(SuiteDataError, match="needs exactly colors"):  # placed per layout now
        sv.axes(bad)
    bad.write_text('[background]\nkind = "visual"\nlevels.dark = { rgba = [0.1, 0.1, 0.1] }\n')
    with pytest.raises(SuiteDataError, match="rgba must be 4 numbers"):
        sv.axes(bad)


@needs_maniskill
def test_each_axis_changes_what_it_claims_and_nothing_else():
    """Visual axes change the camera frame and leave the state; physical axes change the
    bodies and leave the frame; a spec starts the same whatever ran before it."""
    suite = load_suite("simpler/pick_cube:variants=all,obs=images")
    task = suite.tasks[0]
    first = {
        s.variant["axis"] + "." + s.variant["level"]: s
        for s in task.episodes
        if s.seed == task.episodes[0].seed
    }
    env = suite.make_env(task)
    try:
        canonical, info = env.reset(options={"episode": first["canonical.canonical"]})
        assert info["variant"] == "canonical"
        bodies = env._task_bodies()
        mass0 = [b.mass for b in bodies]
        friction0 = [s.physical_material.static_friction for b in bodies for s in b.collision_shapes]
        for key, spec in first.items():
            obs, info = env.reset(options={"episode": spec})
            assert info["variant"] == simpler.sv.label(spec.variant)
            frame = np.abs(obs["base_camera"].astype(int) - canonical["base_camera"]).max()
            np.testing.assert_array_equal(obs["state"], canonical["state"])  # the same layout
            axis = spec.variant["axis"]
            if axis in ("lighting", "table", "camera", "distractors", "background"):
                assert frame > 30, key
            else:
                assert frame == 0, key
            if axis == "distractors":  # in the workspace, beside the object, clear of it and the goal
                scene = env.env.unwrapped.scene
                cubes = [
                    a.pose.p[0].numpy()[:2] for n, a in scene.actors.items() if n.startswith("distractor_")
                ]
                level = simpler.sv.axes()["distractors"].levels[spec.variant["level"]]
                assert len(cubes) == len(level["colors"]), key
                at = {name: start for name, start, _ in simpler.state_layout(simpler.TASKS["pick_cube"])}
                cube_xy = obs["state"][at["obj_pose"] : at["obj_pose"] + 2]
                goal_xy = obs["state"][at["goal_pos"] : at["goal_pos"] + 2]
                near = [float(np.linalg.norm(c - cube_xy)) for c in cubes]
                assert min(near) < simpler.DISTRACTOR_CLEARANCE + 0.02 and all(
                    np.abs(c).max() <= 0.2 for c in cubes
                ), key
                assert all(n >= simpler.DISTRACTOR_CLEARANCE - 1e-6 for n in near), key
                assert all(
                    np.linalg.norm(c - goal_xy) >= simpler.DISTRACTOR_CLEARANCE - 1e-6 for c in cubes
                ), key
            masses = [b.mass for b in env._task_bodies()]
            frictions = [
                s.physical_material.static_friction for b in env._task_bodies() for s in b.collision_shapes
            ]
            scale = (
                simpler.sv.axes()[axis].levels[spec.variant["level"]].get("scale")
                if axis in ("mass", "friction")
                else 1.0
            )
            assert masses == pytest.approx([m * (scale if axis == "mass" else 1.0) for m in mass0]), key
            assert frictions == pytest.approx(
                [f * (scale if axis == "friction" else 1.0) for f in friction0]
            ), key
        again, _ = env.reset(options={"episode": first["canonical.canonical"]})  # after every variant
        np.testing.assert_array_equal(again["base_camera"], canonical["base_camera"])
        assert [b.mass for b in env._task_bodies()] == pytest.approx(mass0)
    finally:
        env.close()


@needs_maniskill
def test_a_variant_run_records_the_variant_column(cli, tmp_path):
    import pandas as pd

    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "simpler/push_cube", "--variants", "mass.heavy+camera.left", "--policy",
        "maniskill_scripted", "--episodes-per-task", "2", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet")
    assert sorted(rows["variant"]) == ["camera=left"] * 2 + ["canonical"] * 2 + ["mass=heavy"] * 2
    assert rows["suite"].unique().tolist() == ["simpler/push_cube:variants=camera.left+mass.heavy"]
    assert rows.groupby("variant")["seed"].apply(tuple).nunique() == 1  # the same two layouts each


@needs_maniskill
def test_an_episode_replays_exactly_in_the_same_env():
    """PhysX keeps contact state across a plain reset, which made 29 of 50 replayed expert
    episodes diverge; the env rebuilds its scene every episode, so none do."""
    from policies.experts.maniskill_scripted import TaskExpert

    suite = load_suite("simpler/stack_cube")
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        for spec in (task.episodes[1], task.episodes[3]):  # both diverged before the rebuild
            runs = []
            for _ in range(2):
                obs, _ = env.reset(options={"episode": spec})
                expert = TaskExpert(task.name, 1.0, layout=simpler.state_layout(simpler.TASKS[task.name]))
                trajectory = []
                for _ in range(task.max_steps):
                    obs, _, _, _, info = env.step(expert.act(obs))
                    trajectory.append(obs)
                    if info["success"]:
                        break
                runs.append(np.array(trajectory))
            np.testing.assert_array_equal(runs[0], runs[1])
    finally:
        env.close()


@needs_maniskill
def test_a_camera_policy_reads_only_the_robots_state_and_its_images(cli, tmp_path):
    """`train --state-features proprio` on image demonstrations: the model reads the
    robot's 16 entries (the env's `proprio_dim`, recorded by collect) and the camera, so
    the object and goal entries of the state change nothing it computes; a student keeps
    the choice; state-only demonstrations are refused (the model would see no objects)."""
    from harness.episode.context import episode_context
    from policies.dvla.checkpoint import load, to_tensors
    from policies.registry import get_policy, parse_params

    demos = tmp_path / "demos"
    suite_name = "simpler/push_cube:obs=images,image_size=32"
    code, _, err = cli(
        "collect", "--suite", suite_name, "--policy", "maniskill_scripted", "--episodes-per-task", "1",
        "--out", str(demos), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    manifest = json.loads((demos / "manifest.json").read_text())
    assert manifest["proprio_dims"] == {"push_cube": 16} and manifest["cameras"] == [simpler.CAMERA]
    tiny = ["--steps", "3", "--batch-size", "8", "--width", "32", "--layers", "1", "--ffn", "64",
            "--chunk-len", "4", "--quiet"]  # fmt: skip
    teacher = tmp_path / "t.safetensors"
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--state-features", "proprio",
        "--image-tokens", "16", "--image-coords", "--out", str(teacher), *tiny,
    )  # fmt: skip
    assert code == 0, err
    ckpt = load(teacher)
    assert ckpt.model.cfg.image_tokens == 16 and ckpt.model.cfg.image_coords
    assert ckpt.model.images.convs[0].in_channels == 5  # RGB + x + y
    assert ckpt.state_prefix == 16 and ckpt.model.cfg.state_dim == 16 and ckpt.raw_state_dim == 26
    assert ckpt.state_features == "proprio" and ckpt.model.cfg.cameras == (simpler.CAMERA,)
    state = np.arange(26, dtype=np.float32)[None]
    moved = state.copy()
    moved[0, 16:] += 5.0  # the cube and the target elsewhere: the model cannot tell
    assert np.array_equal(to_tensors(ckpt, ["x"], state)[1], to_tensors(ckpt, ["x"], moved)[1])

    student = tmp_path / "s.safetensors"
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "distill", "--teacher", str(teacher),
        "--out", str(student), *tiny,
    )  # fmt: skip
    assert code == 0, err
    assert load(student).state_prefix == 16

    spec = get_policy("fast_dvla")
    policy = spec.build(parse_params(spec, {"checkpoint": str(student)}))
    suite = load_suite(suite_name)
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        context = episode_context(suite_name, task, task.episodes[0], env)
        obs, _ = env.reset(options={"episode": task.episodes[0]})
        policy.reset([context])
        assert policy.act([obs]).actions.shape == (1, 4, 7)
    finally:
        env.close()

    state_only = tmp_path / "state-demos"
    code, _, err = cli(
        "collect", "--suite", "simpler/push_cube", "--policy", "maniskill_scripted", "--episodes-per-task",
        "1", "--out", str(state_only), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    code, _, err = cli(
        "train", "--demos", str(state_only), "--recipe", "bidirectional", "--state-features", "proprio",
        "--out", str(tmp_path / "x.safetensors"), *tiny,
    )  # fmt: skip
    assert code == 2 and "no camera images" in err and not (tmp_path / "x.safetensors").exists()
    code, _, err = cli(
        "train", "--demos", str(state_only), "--recipe", "bidirectional", "--image-coords",
        "--out", str(tmp_path / "x.safetensors"), *tiny,
    )  # fmt: skip
    assert code == 2 and "no camera images" in err and not (tmp_path / "x.safetensors").exists()
