"""Thread counts: `--threads`, a default that does not oversubscribe, both
applied to torch before it works and recorded in the manifest. Each case runs in a fresh
interpreter: torch's thread pools are per process and its inter-op count can be set once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from harness.threads import default_threads, physical_cores

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent


def _python(code: str, **env: str) -> dict:
    environ = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        env=environ | env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(("torch_first", "asked"), [(False, 2), (True, 2), (False, None), (True, None)])
def test_threads_reach_torch_whether_or_not_it_is_loaded_yet(torch_first, asked):
    code = (
        ("import torch\n" if torch_first else "")
        + "import json\nfrom harness.threads import apply_threads\n"
        + f"record = apply_threads({asked})\n"
        + "import torch\n"
        + f"record = apply_threads({asked})\n"  # as `run` does once the policies loaded torch
        + "record['now'] = [torch.get_num_threads(), torch.get_num_interop_threads()]\n"
        + "print(json.dumps(record))"
    )
    record = _python(code)
    want = asked or 1
    assert record["threads"] == want
    assert record["now"] == [want, want]  # intra-op and inter-op, where still legal
    assert record["requested"] == asked
    assert record["source"] == ("--threads" if asked else "default")


def test_a_users_omp_num_threads_is_kept_and_said_where_it_came_from():
    code = (
        "import json\nfrom harness.threads import apply_threads\n"
        "apply_threads()\nimport torch\nr = apply_threads()\n"
        "r['now'] = torch.get_num_threads()\nprint(json.dumps(r))"
    )
    record = _python(code, OMP_NUM_THREADS="3")
    assert (record["threads"], record["source"], record["now"]) == (3, "OMP_NUM_THREADS", 3)


def test_the_default_never_gives_a_worker_more_than_its_share_of_the_cores():
    cores = physical_cores()
    assert default_threads() == 1
    assert default_threads(workers=cores * 4) == 1
    assert 1 <= cores <= (os.cpu_count() or 1)


def test_run_records_asked_and_effective_threads_and_refuses_a_bad_count(cli, tmp_path):
    code = (
        "import json, sys\nfrom harness.cli import main\n"
        f"rc = main(['run', '--suite', 'metaworld/mt1/reach-v3', '--policy', 'bidirectional', "
        f"'--episodes-per-task', '1', '--threads', '2', '--quiet', '--out', {str(tmp_path / 'r')!r}])\n"
        f"m = json.load(open({str(tmp_path / 'r' / 'manifest.json')!r}))\n"
        "print(json.dumps(m['threads'] | {'rc': rc, 'cal': m['calibration']['torch_threads']}))"
    )
    record = _python(code)
    assert record["rc"] == 0
    assert (record["requested"], record["source"], record["threads"]) == (2, "--threads", 2)
    assert (record["torch_intra_op"], record["torch_interop"], record["cal"]) == (2, 2, 2)
    code, _, err = cli("run", "--policy", "scripted", "--threads", "0", "--out", str(tmp_path / "x"))
    assert code == 2 and "--threads" in err and "1..1024" in err
    assert not (tmp_path / "x").exists()
