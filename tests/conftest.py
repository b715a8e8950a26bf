from __future__ import annotations

import pytest

from harness.cli import main


@pytest.fixture
def cli(capsys):
    """Run the CLI in-process; returns (exit status, stdout, stderr)."""

    def invoke(*argv: str) -> tuple[int, str, str]:
        try:
            code = main(list(argv))
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code if isinstance(exc.code, int) else 1
        captured = capsys.readouterr()
        return code, captured.out, captured.err

    return invoke


@pytest.fixture
def one_torch_thread():
    """One torch thread, as CI and every baseline run (OMP_NUM_THREADS=1); restored after."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def chain_data(tmp_path, monkeypatch):
    """A copy of the shipped chain data (scenes, chain files, their hashes) that the chain
    loaders read instead, so a test can edit it; the loaders' caches cleared around it."""
    from adapters import chain_scenes as cs

    folder = tmp_path / "chain_data"
    folder.mkdir()
    for path in cs.DATA.iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    monkeypatch.setattr(cs, "DATA", folder)
    cs.load_scene.cache_clear()
    cs.load_chains.cache_clear()
    yield folder
    cs.load_scene.cache_clear()
    cs.load_chains.cache_clear()


@pytest.fixture(scope="session")
def demos(tmp_path_factory):
    """Tiny Meta-World demonstrations (2 tasks x 2 episodes) for training tests."""
    out = tmp_path_factory.mktemp("demos") / "mt"
    assert (
        main(
            [
                "collect",
                "--suite",
                "metaworld/mt10",
                "--tasks",
                "reach-v3,drawer-close-v3",
                "--policy",
                "scripted",
                "--episodes-per-task",
                "2",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    return out
