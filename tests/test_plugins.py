"""Third-party policies and suites arrive through real entry points of an installed dist."""

from __future__ import annotations

import sys
import textwrap

import pytest

from adapters.registry import list_suites, load_suite
from policies.registry import all_policies, get_policy

PLUGIN = """
from dataclasses import dataclass
import gymnasium as gym
import numpy as np
from adapters.base import EpisodeSpec, Suite, SuiteInfo, TaskSpec
from adapters.registry import SuiteProvider
from policies.base import ChunkBatch
from policies.registry import PolicySpec, param

@dataclass(frozen=True)
class Params:
    value: float = param(0.5, "the constant action", low=-1.0, high=1.0)

class Constant:
    def __init__(self, params): self.params = params
    def reset(self, episodes): pass
    def act(self, observations): return ChunkBatch(actions=np.full((1, 1, 2), self.params.value))

SPEC = PolicySpec(name="constant", summary="a constant action", params=Params, build=Constant)

class Line(gym.Env):
    observation_space = gym.spaces.Box(-10, 10, (1,))
    action_space = gym.spaces.Box(-1, 1, (2,))
    def reset(self, *, seed=None, options=None):
        self.x = 0.0
        return np.array([self.x]), {"success": False}
    def step(self, action):
        self.x += float(action[0])
        return np.array([self.x]), 0.0, False, False, {"success": self.x >= 2.0}

TASK = TaskSpec("walk", "walk two units", 10, tuple(EpisodeSpec(i, seed=i) for i in range(3)))
SUITE = Suite("line/walk", "1", (TASK,), lambda task: Line())
PROVIDER = SuiteProvider(
    prefix="line/",
    list_suites=lambda: [SuiteInfo("line/walk", "walk along a line", 1, 3, "", True)],
    load_suite=lambda name, split: SUITE,
)
NOT_A_SPEC = object()
"""


@pytest.fixture
def installed_plugin(tmp_path, monkeypatch):
    (tmp_path / "dvla_line_plugin.py").write_text(PLUGIN)
    dist = tmp_path / "dvla_line_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: dvla-line-plugin\nVersion: 0.1\n")
    entry_points = textwrap.dedent("""
        [dvla_harness.policies]
        constant = dvla_line_plugin:SPEC
        [dvla_harness.adapters]
        line = dvla_line_plugin:PROVIDER
    """)
    (dist / "entry_points.txt").write_text(entry_points)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield dist
    sys.modules.pop("dvla_line_plugin", None)


def test_plugin_policy_and_suite_run_end_to_end(installed_plugin, cli, tmp_path):
    assert get_policy("constant").summary == "a constant action"
    assert "line/walk" in [s.name for s in list_suites()]
    assert load_suite("line/walk").tasks[0].name == "walk"
    code, out, _ = cli(
        "run",
        "--suite",
        "line/walk",
        "--policy",
        "constant:value=1.0",
        "--out",
        str(tmp_path / "r"),
        "--quiet",
    )
    assert code == 0 and "3/3" in out
    code, _, err = cli(
        "run", "--suite", "line/walk", "--policy", "constant:value=2", "--out", str(tmp_path / "s")
    )
    assert code == 2 and "value=2.0 is out of range; valid range [-1.0, 1.0]" in err


def test_a_plugin_naming_the_wrong_kind_of_object_is_reported(installed_plugin):
    text = (installed_plugin / "entry_points.txt").read_text().replace(":SPEC", ":NOT_A_SPEC")
    (installed_plugin / "entry_points.txt").write_text(text)
    with pytest.raises(
        TypeError, match=r"entry point 'constant' in dvla_harness\.policies must be a PolicySpec"
    ):
        all_policies()
