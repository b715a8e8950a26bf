"""`dvla-harness check`: the contract as rules, one line each, exit 1 on any failure; on
the built-in suites (which must pass) and on plugin code broken one rule at a time."""

from __future__ import annotations

import pytest

from tests.test_plugins import installed_plugin  # noqa: F401  (the fixture)

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def test_builtin_suite_and_policy_pass(cli):
    # Before its fix, Meta-World's env returned the goal outside its own observation space.
    code, out, _ = cli("check", "suite", "metaworld/mt1/reach-v3", "--steps", "20")
    assert code == 0 and "all rules hold" in out and "FAIL" not in out
    code, out, _ = cli("check", "policy", "fast_dvla", "--suite", "metaworld/mt1/reach-v3")
    assert code == 0 and "parameters round-trip through JSON" in out and "inside the action space" in out


def _break(dist, old: str, new: str) -> None:
    module = dist.parent / "dvla_line_plugin.py"
    text = module.read_text()
    assert old in text
    module.write_text(text.replace(old, new))


def test_a_conforming_plugin_passes(installed_plugin, cli):  # noqa: F811
    code, out, err = cli("check", "suite", "line/walk")
    assert code == 0 and "all rules hold" in out, out + err
    code, out, err = cli("check", "policy", "constant:value=1.0", "--suite", "line/walk")
    assert code == 0 and "all rules hold" in out, out + err


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        (
            'return np.array([self.x]), {"success": False}',
            "return np.array([self.x]), {}",
            "must hold a bool 'success'",
        ),
        (
            '{"success": self.x >= 2.0}',
            '{"success": 1.0 if self.x >= 2.0 else 0.0}',
            "info['success'] must be a bool",
        ),
        (
            "self.x = 0.0",
            "self.x = float(np.random.uniform(-1, 1))",
            "the same episode spec gave another first observation",
        ),
        (
            "return np.array([self.x]), 0.0, False, False,",
            "return np.array([self.x]), 0.0, False,",
            "step returned 4 values",
        ),
    ],
)
def test_a_suite_breaking_one_rule_fails_that_rule(installed_plugin, cli, old, new, needle):  # noqa: F811
    _break(installed_plugin, old, new)
    code, out, _ = cli("check", "suite", "line/walk")
    assert code == 1 and needle in out and "1 rule(s) failed" in out


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        (
            "np.full((1, 1, 2), self.params.value)",
            "np.full((1, 1, 3), self.params.value)",
            "the contract is (batch 1, chunk, 2)",
        ),
        (
            "np.full((1, 1, 2), self.params.value)",
            "np.full((1, 1, 2), 5.0)",
            "element 0 is 5, bounds [-1, 1]",
        ),
        (
            "np.full((1, 1, 2), self.params.value)",
            "np.full((1, 1, 2), np.nan)",
            "actions must be finite floats",
        ),
    ],
)
def test_a_policy_breaking_one_rule_fails_that_rule(installed_plugin, cli, old, new, needle):  # noqa: F811
    _break(installed_plugin, old, new)
    code, out, _ = cli("check", "policy", "constant", "--suite", "line/walk")
    assert code == 1 and needle in out


def test_check_usage_errors(cli):
    code, _, err = cli("check", "policy", "random")
    assert code == 2 and "needs --suite" in err
    code, _, err = cli("check", "suite", "nope/x")
    assert code == 2 and "unknown suite" in err
    code, _, err = cli("check", "policy", "nope", "--suite", "metaworld/mt10")
    assert code == 2 and "unknown policy 'nope'" in err
