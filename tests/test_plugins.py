"""Third-party policies and suites arrive through real entry points of an installed dist."""

from __future__ import annotations

import json
import sys
import textwrap

import pytest

from adapters.registry import list_suites, load_suite
from policies.registry import all_policies, get_policy

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

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
    monkeypatch.setattr("harness.plugins._warned", set())  # each test sees its own warnings
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


def _entry_points(dist, text: str) -> None:
    (dist / "entry_points.txt").write_text(textwrap.dedent(text))


def test_a_plugin_naming_the_wrong_kind_of_object_is_skipped_with_a_warning(installed_plugin, capsys):
    text = (installed_plugin / "entry_points.txt").read_text().replace(":SPEC", ":NOT_A_SPEC")
    (installed_plugin / "entry_points.txt").write_text(text)
    policies = all_policies()
    assert "constant" not in policies and "random" in policies
    err = capsys.readouterr().err
    assert (
        "plugin dvla-line-plugin 0.1: entry point 'constant' (dvla_harness.policies) must name a PolicySpec"
        in err
    )


def test_a_broken_plugin_cannot_break_listing_or_running(installed_plugin, cli, tmp_path):
    _entry_points(
        installed_plugin,
        """
        [dvla_harness.policies]
        constant = dvla_line_plugin:SPEC
        broken = dvla_no_such_module:SPEC
        [dvla_harness.adapters]
        line = dvla_line_plugin:PROVIDER
        broken = dvla_line_plugin:MISSING_NAME
        """,
    )
    code, out, err = cli("list", "suites")
    assert code == 0 and "line/walk" in out and "metaworld/mt10" in out
    assert "entry point 'broken' (dvla_harness.adapters) failed to load (AttributeError" in err
    code, out, err = cli("list", "policies")
    assert code == 0 and "constant" in out and "fast_dvla" in out
    assert "entry point 'broken' (dvla_harness.policies) failed to load (ModuleNotFoundError" in err
    code, _, err = cli(
        "run", "--suite", "line/walk", "--policy", "constant", "--out", str(tmp_path / "r"), "--quiet"
    )
    assert code == 0, err


def test_a_plugin_may_not_take_a_name_the_harness_has(installed_plugin, cli, tmp_path):
    plugin = (installed_plugin.parent / "dvla_line_plugin.py").read_text()
    plugin += "\nRANDOM = PolicySpec(name='random', summary='an impostor', params=Params, build=Constant)\n"
    plugin += (
        "META = SuiteProvider(prefix='metaworld/', list_suites=lambda: [], load_suite=lambda n, s: SUITE)\n"
    )
    (installed_plugin.parent / "dvla_line_plugin.py").write_text(plugin)
    _entry_points(
        installed_plugin,
        """
        [dvla_harness.policies]
        random = dvla_line_plugin:RANDOM
        [dvla_harness.adapters]
        meta = dvla_line_plugin:META
        """,
    )
    code, _, err = cli("run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--episodes-per-task", "1",
                         "--out", str(tmp_path / "r"), "--quiet")  # fmt: skip
    assert code == 0, err
    assert "registers policy 'random', which dvla-harness already provides; the plugin's is ignored" in err
    assert "registers suites under 'metaworld/', which overlaps 'metaworld/' from dvla-harness" in err
    assert get_policy("random").summary != "an impostor"
    manifest = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert manifest["policies"][0]["provided_by"] == "dvla-harness"
    assert manifest["suite"]["provided_by"] == "dvla-harness"


def test_the_manifest_names_the_plugin_that_provided_policy_and_suite(installed_plugin, cli, tmp_path):
    code, _, err = cli(
        "run", "--suite", "line/walk", "--policy", "constant", "--out", str(tmp_path / "r"), "--quiet"
    )
    assert code == 0, err
    manifest = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert manifest["policies"][0]["provided_by"] == "dvla-line-plugin 0.1"
    assert manifest["suite"]["provided_by"] == "dvla-line-plugin 0.1"


def test_a_provider_that_raises_is_exit_2_naming_the_plugin(installed_plugin, cli, tmp_path):
    plugin = (installed_plugin.parent / "dvla_line_plugin.py").read_text()
    plugin += "\ndef _boom(name, split):\n    raise RuntimeError('the plugin is broken')\n"
    plugin += "PROVIDER = SuiteProvider(prefix='line/', list_suites=lambda: [], load_suite=_boom)\n"
    (installed_plugin.parent / "dvla_line_plugin.py").write_text(plugin)
    out = tmp_path / "r"
    code, _, err = cli("run", "--suite", "line/walk", "--policy", "constant", "--out", str(out))
    assert code == 2 and not out.exists()
    assert (
        "suite 'line/walk': its provider (dvla-line-plugin 0.1) raised RuntimeError: the plugin is broken"
        in err
    )


def test_list_suites_shows_the_extra_in_brackets(installed_plugin, cli):
    module = installed_plugin.parent / "dvla_line_plugin.py"
    text = module.read_text().replace(
        '"walk along a line", 1, 3, "", True', '"walk along a line", 1, 3, "linesim", False'
    )
    module.write_text(text)
    code, out, _ = cli("list", "suites")
    assert code == 0 and "pip install 'dvla-line-plugin[linesim]'" in out  # the plugin's extra, brackets kept


def test_the_plugin_guide_installs_with_pip_and_runs(tmp_path, monkeypatch, cli):
    """docs/plugins.md's example package, as written: pip installs it, the harness lists and
    runs its policy and suite, and its validate() and check_spaces() rules hold."""
    import re
    import subprocess
    from pathlib import Path

    doc = (Path(__file__).resolve().parent.parent / "docs" / "plugins.md").read_text()

    def block(marker: str) -> str:
        return re.search(rf"<!-- plugin:{marker} -->\n```\w+\n(.+?)\n```", doc, re.S).group(1)

    package = tmp_path / "dvla-line-plugin"
    package.mkdir()
    (package / "pyproject.toml").write_text(block("pyproject"))
    (package / "dvla_line_plugin.py").write_text(block("module"))
    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(site), str(package)],
        check=True, capture_output=True,
    )  # fmt: skip
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr("harness.plugins._warned", set())
    try:
        code, out, err = cli("list", "policies")
        assert code == 0 and "constant" in out and "a plugin example" in out, err
        out_dir = tmp_path / "run"
        code, out, err = cli(
            "run", "--suite", "line/walk", "--policy", "constant:value=1.0", "--out", str(out_dir)
        )
        assert code == 0 and "5/5" in out, err
        manifest = json.loads((out_dir / "manifest.json").read_text())
        assert manifest["policies"][0]["provided_by"] == "dvla-line-plugin 0.1.0"
        code, _, err = cli(
            "run", "--suite", "line/walk", "--policy", "constant:value=0", "--out", str(tmp_path / "z")
        )
        assert code == 2 and "value=0 never moves" in err
        code, _, err = cli(
            "run", "--suite", "line/nope", "--policy", "constant", "--out", str(tmp_path / "n")
        )
        assert code == 2 and "line suites: line/walk" in err
    finally:
        sys.modules.pop("dvla_line_plugin", None)


def test_a_plugin_suite_missing_its_simulator_names_the_plugin_not_an_empty_extra(
    installed_plugin, cli, tmp_path
):
    module = installed_plugin.parent / "dvla_line_plugin.py"
    plain = module.read_text()
    missing = 'Suite("line/walk", "1", (TASK,), lambda task: Line(), simulator_packages=("no_such_sim",)'
    module.write_text(plain.replace('Suite("line/walk", "1", (TASK,), lambda task: Line()', missing))
    code, _, err = cli("run", "--suite", "line/walk", "--policy", "constant", "--out", str(tmp_path / "r"))
    assert (
        code == 2 and "suite 'line/walk' (from dvla-line-plugin 0.1) needs no_such_sim: install them" in err
    )
    assert "dvla-harness[]" not in err
    module.write_text(
        plain.replace('Suite("line/walk", "1", (TASK,), lambda task: Line()', missing + ', extra="linesim"')
    )
    sys.modules.pop("dvla_line_plugin", None)
    code, _, err = cli("run", "--suite", "line/walk", "--policy", "constant", "--out", str(tmp_path / "s"))
    assert code == 2 and "pip install 'dvla-line-plugin[linesim]'" in err  # the plugin's extra, not ours


@pytest.mark.parametrize(
    "name",
    [
        "SuiteProvider",
        "SuiteInfo",
        "Suite",
        "TaskSpec",
        "EpisodeSpec",
        "PolicySpec",
        "EpisodeContext",
        "ChunkBatch",
    ],
)
def test_the_plugin_reference_lists_every_field_in_order(name):
    """docs/plugins.md's reference tables are the dataclasses: every field, in order, and
    'required' (no default) exactly where the dataclass has no default."""
    import dataclasses
    import re
    from pathlib import Path

    from adapters import base, registry
    from policies import base as policy_base
    from policies import registry as policy_registry

    kinds = {m.__name__: m for m in (base, registry, policy_base, policy_registry)}
    cls = next(getattr(m, name) for m in kinds.values() if hasattr(m, name))
    doc = (Path(__file__).resolve().parent.parent / "docs" / "plugins.md").read_text()
    section = doc.split(f"<!-- reference:{name} -->")[1].split("<!-- reference:")[0]
    rows = re.findall(r"^\| `(\w+)` \|[^|]+\|([^|]*)\|", section, re.M)
    fields = dataclasses.fields(cls)
    assert [r[0] for r in rows] == [f.name for f in fields]
    for (field_name, default), f in zip(rows, fields, strict=True):
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        assert (default.strip() == "") == required, field_name
