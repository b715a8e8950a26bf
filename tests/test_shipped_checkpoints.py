"""The reference checkpoints this repository ships: small, loadable, and skilled."""

from __future__ import annotations

import hashlib

import pytest

from adapters import libero, simpler
from policies.dvla.checkpoint import load
from policies.dvla.policy import SHIPPED
from results.store import RunDir

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

EXPECTED = {
    "bidirectional": "bidirectional",
    "fast_dvla": "block_causal",
    "block_diffusion": "block_causal",
    "autoregressive": "causal",
}


def test_shipped_checkpoints_load_with_their_provenance():
    files = {name: SHIPPED / f"metaworld-mt10-{name}.safetensors" for name in EXPECTED}
    # Everything shipped, every suite's set together, stays small enough to commit (the
    # two chain sets' eight files, 192 wide and 6 deep, are 11.7 MB each; the others 3.7-4.1).
    assert sum(f.stat().st_size for f in SHIPPED.glob("*.safetensors")) < 160 * 2**20
    for name, path in files.items():
        ckpt = load(path)
        assert ckpt.model.cfg.pattern == EXPECTED[name]
        assert ckpt.meta["data_sha256"] and ckpt.meta["recipe"]
    teacher, student = load(files["bidirectional"]), load(files["fast_dvla"])
    assert student.meta["recipe"] == "distill" and student.vocab == teacher.vocab
    # The student names its teacher by content: the shipped teacher, not some other file.
    assert student.meta["teacher_sha256"] == hashlib.sha256(files["bidirectional"].read_bytes()).hexdigest()
    # Bins span the executed actions ([-1, 1] on Meta-World), so decoding is precise.
    assert teacher.meta["tokenizer_round_trip_error"] < 0.005


def test_the_paper_recipe_student_is_the_shipped_teachers_distilled_with_d2f_noise():
    """`metaworld-mt10-d2f` is a set of one file: the student a `fast_dvla` policy gets by
    set name, distilled from the shipped teacher (by content) under D2F's schedule, on the
    data the shipped student saw (the same steps; its folders' combined hash differs)."""
    from policies.registry import get_policy, parse_params

    path = SHIPPED / "metaworld-mt10-d2f-fast_dvla.safetensors"
    params = parse_params(get_policy("fast_dvla"), {"checkpoint": "metaworld-mt10-d2f"})
    assert params.checkpoint == str(path)
    student, shipped = load(path), load(SHIPPED / "metaworld-mt10-fast_dvla.safetensors")
    config = student.meta["train_config"]
    assert (config["recipe"], config["noise_schedule"]) == ("distill", "d2f")
    assert config["noise_schedule"] != shipped.meta["train_config"]["noise_schedule"]
    for key in ("steps", "batch_size", "lr", "seed", "width", "layers"):
        assert config[key] == shipped.meta["train_config"][key], key
    teacher = SHIPPED / "metaworld-mt10-bidirectional.safetensors"
    assert student.meta["teacher_sha256"] == hashlib.sha256(teacher.read_bytes()).hexdigest()
    assert student.model.cfg.pattern == "block_causal" and student.vocab == shipped.vocab


@pytest.mark.parametrize("policy", ["bidirectional", "fast_dvla"])
def test_shipped_policy_solves_easy_mt10_tasks_with_no_arguments(cli, tmp_path, policy):
    code, _, err = cli(
        "run",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        "door-open-v3,drawer-close-v3",
        "--episodes-per-task",
        "3",
        "--policy",
        policy,
        "--out",
        str(tmp_path / "r"),
        "--quiet",
    )
    assert code == 0, err
    per_task = RunDir(tmp_path / "r").read_episodes().groupby("task")["success"].sum()
    assert (per_task >= 2).all(), per_task.to_dict()


@pytest.mark.parametrize("name", ["libero-spatial", "libero-object"])
def test_shipped_libero_sets_are_a_teacher_its_student_and_an_ar_baseline(name):
    teacher = load(SHIPPED / f"{name}-bidirectional.safetensors")
    student = load(SHIPPED / f"{name}-fast_dvla.safetensors")
    ar = load(SHIPPED / f"{name}-autoregressive.safetensors")
    assert (teacher.model.cfg.pattern, student.model.cfg.pattern, ar.model.cfg.pattern) == (
        "bidirectional",
        "block_causal",
        "causal",
    )
    # One suite's observations and instructions. Not the same data hash: a set may mix
    # collections of the suite (revisions of the expert; today both sets happen to match).
    assert teacher.model.cfg.action_dim == ar.model.cfg.action_dim == 7
    assert teacher.vocab == ar.vocab and teacher.meta["state_dims"] == ar.meta["state_dims"]
    digest = hashlib.sha256((SHIPPED / f"{name}-bidirectional.safetensors").read_bytes()).hexdigest()
    assert student.meta["teacher_sha256"] == digest


def test_the_spatial_block_diffusion_file_is_the_shipped_teacher_fine_tuned_on_its_data():
    """The set's fifth decoder (docs/latency.md's LIBERO rows): fine-tuned from the
    shipped teacher by content, on the very demonstrations the teacher saw, so its rows
    differ from the teacher's by the block-causal recipe alone."""
    teacher = load(SHIPPED / "libero-spatial-bidirectional.safetensors")
    bd = load(SHIPPED / "libero-spatial-block_diffusion.safetensors")
    assert bd.model.cfg.pattern == "block_causal" and bd.meta["recipe"] == "block_diffusion"
    digest = hashlib.sha256((SHIPPED / "libero-spatial-bidirectional.safetensors").read_bytes()).hexdigest()
    assert bd.meta["init_sha256"] == digest
    assert bd.meta["data_sha256"] == teacher.meta["data_sha256"]
    assert bd.vocab == teacher.vocab and bd.meta["state_dims"] == teacher.meta["state_dims"]
    assert all(source["fresh_initial_states"] for source in bd.meta["data_sources"])


def test_shipped_simpler_sets_are_state_and_camera_policies_with_their_teachers():
    state = {name: load(SHIPPED / f"simpler-state-{name}.safetensors") for name in EXPECTED}
    for name, ckpt in state.items():
        assert ckpt.model.cfg.pattern == EXPECTED[name] and ckpt.state_features == "relative"
        assert not ckpt.model.cfg.cameras
    camera = {
        name: load(SHIPPED / f"simpler-img64-{name}.safetensors") for name in ("bidirectional", "fast_dvla")
    }
    for ckpt in camera.values():
        # Only the robot's own state: where the cubes are must come from the pixels, so the
        # visual variants reach this policy.
        assert ckpt.state_features == "proprio" and ckpt.model.cfg.cameras
        assert ckpt.model.cfg.image_size == 64 and ckpt.model.cfg.image_coords
    for prefix, teacher in (
        ("simpler-state", state["bidirectional"]),
        ("simpler-img64", camera["bidirectional"]),
    ):
        digest = hashlib.sha256((SHIPPED / f"{prefix}-bidirectional.safetensors").read_bytes()).hexdigest()
        student = state["fast_dvla"] if prefix == "simpler-state" else camera["fast_dvla"]
        assert student.meta["teacher_sha256"] == digest and student.vocab == teacher.vocab
    assert (
        state["block_diffusion"].meta["init_sha256"]
        == hashlib.sha256((SHIPPED / "simpler-state-bidirectional.safetensors").read_bytes()).hexdigest()
    )


@pytest.mark.skipif(not simpler._installed(), reason="needs the maniskill extra")
def test_the_shipped_simpler_teacher_pulls_the_cube_by_set_name(cli, tmp_path):
    # The set's name, not a path: it resolves to the teacher's file of the shipped set.
    args = (
        "run --suite simpler/pull_cube --episodes-per-task 3 --policy bidirectional:checkpoint=simpler-state"
    )
    code, _, err = cli(*args.split(), "--out", str(tmp_path / "r"), "--quiet")
    assert code == 0, err
    episodes = RunDir(tmp_path / "r").read_episodes()
    assert episodes["checkpoint"].str.endswith("simpler-state-bidirectional.safetensors").all()
    assert episodes["success"].sum() >= 2, episodes[["episode_index", "success"]].to_dict("records")


def test_the_shipped_chain_set_reads_the_goal_positions_state():
    """The tray-scene set was trained with `goal_positions=on`: its state is
    the scene's plus the goal's two positions, and every recipe says so in its sources."""
    chain = {name: load(SHIPPED / f"chains-tray-{name}.safetensors") for name in EXPECTED}
    for name, ckpt in chain.items():
        assert ckpt.model.cfg.pattern == EXPECTED[name] and ckpt.state_features == "relative"
        suites = {s["suite"] for s in ckpt.meta["data_sources"]}
        assert suites and all(s.startswith("chains/living_room_scene3:") for s in suites)
        assert all("goal_positions=on" in s for s in suites), suites
        assert ckpt.state_positions[-2:] == (61, 64) and ckpt.raw_state_dim == 67
    digest = hashlib.sha256((SHIPPED / "chains-tray-bidirectional.safetensors").read_bytes()).hexdigest()
    assert chain["fast_dvla"].meta["teacher_sha256"] == digest
    assert chain["block_diffusion"].meta["init_sha256"] == digest


def test_the_language_only_chain_set_reads_the_instruction_and_the_scene_only():
    """The libero_goal set is CALVIN's protocol: the instruction and the scene's state,
    no goal positions; all four recipes read the same state and vocabulary, the student
    and block diffusion name the shipped teacher by content."""
    chain = {name: load(SHIPPED / f"chains-goal-{name}.safetensors") for name in EXPECTED}
    teacher = chain["bidirectional"]
    for name, ckpt in chain.items():
        assert ckpt.model.cfg.pattern == EXPECTED[name] and ckpt.state_features == "relative"
        suites = {s["suite"] for s in ckpt.meta["data_sources"]}
        assert suites and all(s.startswith("chains/libero_goal:") for s in suites)
        assert not any("goal_positions" in s for s in suites), suites
        assert ckpt.raw_state_dim == teacher.raw_state_dim and ckpt.vocab == teacher.vocab
    digest = hashlib.sha256((SHIPPED / "chains-goal-bidirectional.safetensors").read_bytes()).hexdigest()
    assert chain["fast_dvla"].meta["teacher_sha256"] == digest
    assert chain["block_diffusion"].meta["init_sha256"] == digest


@pytest.mark.skipif(not libero.installed(), reason="needs the libero extra")
def test_the_language_only_chain_set_is_refused_on_the_goal_positions_suite(cli, tmp_path):
    out = tmp_path / "r"
    suite = "chains/libero_goal:goal_positions=on"
    args = f"run --suite {suite} --episodes-per-task 1 --policy fast_dvla:checkpoint=chains-goal"
    code, _, err = cli(*args.split(), "--out", str(out), "--quiet")
    assert code == 2 and "chains/libero_goal" in err and "trained on" in err, err
    assert not out.exists()


@pytest.mark.skipif(not libero.installed(), reason="needs the libero extra")
def test_the_chain_set_on_the_language_only_suite_names_the_option(cli, tmp_path):
    out = tmp_path / "r"
    args = "run --suite chains/living_room_scene3 --episodes-per-task 1 --policy bidirectional:checkpoint=chains-tray"
    code, _, err = cli(*args.split(), "--out", str(out), "--quiet")
    assert code == 2 and "goal_positions=on" in err, err
    assert not out.exists()


def paper_deviations(train_config: dict) -> str:
    """What a checkpoint's training does that its recipe's paper does not, read from its
    header's train_config (the shared ones, model size and data, are stated once above
    the README's table): Fast-dVLA distils with D2F's noise profile and LoRA rank 32,
    BD3-LM trains block diffusion with clean context, neither adds other losses."""
    recipe, schedule = train_config["recipe"], train_config.get("noise_schedule", "")
    out = []
    if recipe == "distill":
        if schedule != "d2f":
            out.append(f"`{schedule}` noise schedule (paper: D2F's rising profile, `--noise-schedule d2f`)")
        out.append("full fine-tuning (paper: LoRA rank 32)")
        if train_config.get("demo_ce", 0.0):
            out.append(f"`--demo-ce {train_config['demo_ce']}` (not in the paper)")
    if recipe == "block_diffusion" and schedule != "clean_context":
        out.append(f"`{schedule}` noise schedule (BD3-LM: clean context)")
    if train_config.get("ema", 0.0):
        out.append(f"`--ema {train_config['ema']}` (not in the paper)")
    return "; ".join(out) or "none beyond those shared by every set"


def test_the_checkpoint_readme_names_each_checkpoints_deviations_from_its_paper():
    """Every shipped checkpoint has a row, and its deviations are its header's, so a
    retrained file with another schedule or loss cannot keep a stale label."""
    import json

    readme = (SHIPPED / "README.md").read_text()
    sidecars = sorted(SHIPPED.glob("*.json"))
    assert len(sidecars) == len(list(SHIPPED.glob("*.safetensors")))
    for sidecar in sidecars:
        train_config = json.loads(sidecar.read_text())["meta"]["train_config"]
        row = next((line for line in readme.splitlines() if line.startswith(f"| `{sidecar.stem}` |")), None)
        assert row, f"{sidecar.stem} has no row in policies/checkpoints/README.md"
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == train_config["recipe"] and cells[-1] == paper_deviations(train_config), row
    # the shipped students are not trained with the paper's schedule, and the table says so
    assert "`frontier` noise schedule" in readme and "`--demo-ce 0.5` (not in the paper)" in readme
