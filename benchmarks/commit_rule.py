"""What pipelined decoding's commit rule costs: the tokens it commits below tau_conf.

A fully activated Fast-dVLA block with R masked tokens commits every token whose
confidence reaches min(tau_conf, the k-th highest), k = floor(R / n): at least R / n
tokens per pass, however unsure the model is. A small model's confidences are rarely
sharp, so that floor decides many tokens. This script measures, for a block-causal
student under several decoder settings and its bidirectional teacher, on demonstration
states (the same rows for every setting):

    NFE/chunk          forward passes per chunk;
    below tau_conf     share of committed tokens whose confidence at commit was below
                       tau_conf (committed by the k-th-highest floor or the one-token
                       progress rule, not because the model was sure);
    = teacher          share of tokens equal to the teacher's decode of the same state,
                       for all tokens and for those committed below / at tau_conf;
    = demo             share equal to the demonstrated chunk's tokens;
    L1 to demo         mean |action - demonstrated action| over the chunk, in action units.

Confidence at commit is read by wrapping the decoder's two commit functions
(`commit_semi`, `commit_full` in policies/dvla/fast_dvla.py) for the length of this
script: the decoder itself is unchanged, and its passes say which positions each call's
commits were.

    python benchmarks/commit_rule.py --demos demos/chains-tray-goal-s0 [more folders] \\
        --student policies/checkpoints/chains-tray-fast_dvla.safetensors \\
        --teacher policies/checkpoints/chains-tray-bidirectional.safetensors \\
        [--settings "n=2;n=3;n=4;tau_add=1,tau_act=1"] [--samples 512] [--batch 64] \\
        [--json benchmarks/results/commit-rule.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from harness.config import parse_policy_arg
from policies.registry import get_policy, parse_params


@contextmanager
def recording_commits() -> Iterator[list[np.ndarray]]:
    """Per call of a fast_dvla commit function, in call order: the confidences of the
    tokens it committed (ascending position)."""
    from policies.dvla import fast_dvla

    calls: list[np.ndarray] = []
    semi, full = fast_dvla.commit_semi, fast_dvla.commit_full

    def wrap(rule: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
        def recorded(masked: np.ndarray, conf: np.ndarray, *args: Any) -> np.ndarray:
            commit = rule(masked, conf, *args)
            calls.append(np.asarray(conf)[commit].astype(float))
            return commit

        return recorded

    fast_dvla.commit_semi, fast_dvla.commit_full = wrap(semi), wrap(full)
    try:
        yield calls
    finally:
        fast_dvla.commit_semi, fast_dvla.commit_full = semi, full


def commit_confidence(passes: list[Any], calls: list[np.ndarray], rows: int, total: int) -> np.ndarray:
    """(rows, total) confidence each token had when committed. The decoder calls the
    commit functions pass by pass, row by row, block by block in position order, and
    each pass records a row's commits sorted, so both streams run in the same order."""
    stream = np.concatenate(calls) if calls else np.zeros(0)
    out = np.full((rows, total), np.nan)
    at = 0
    for p in passes:
        for row, committed in enumerate(p.committed):
            out[row, committed] = stream[at : at + len(committed)]
            at += len(committed)
    if at != len(stream):
        raise RuntimeError(f"commit record out of step: {len(stream)} recorded, {at} in the passes")
    return out


def build(spec_text: str, checkpoint: str) -> tuple[Any, Any, bool]:
    """(policy, params, is fast_dvla) for one decoder setting, as `--policy` builds it."""
    choice = parse_policy_arg(spec_text)
    spec = get_policy(choice.name)
    params = parse_params(spec, {"checkpoint": checkpoint, **choice.params})
    return spec.build(params), params, choice.name == "fast_dvla"


def decode(
    policy: Any, params: Any, pipelined: bool, words: Any, states: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(tokens, NFE per row, confidence at commit or None) for one batch. A row's NFE is
    the passes up to its last commit: in a batch, a finished row waits for the others."""
    import torch

    with torch.inference_mode(), recording_commits() as calls:
        decoded = policy._decode(policy.model, words, states, params)
    tokens = decoded.tokens.cpu().numpy()
    nfe = np.array(
        [1 + max(i for i, p in enumerate(decoded.passes) if p.committed[row]) for row in range(len(tokens))]
    )
    conf = commit_confidence(decoded.passes, calls, *tokens.shape) if pipelined else None
    return tokens, nfe, conf


def measure(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from policies.dvla.checkpoint import load, to_tensors
    from policies.dvla.demos import load_demos

    torch.set_num_threads(args.threads)
    student, teacher = load(args.student), load(args.teacher)
    if student.tokenizer.to_dict() != teacher.tokenizer.to_dict():
        raise ValueError(
            f"{args.student} and {args.teacher} tokenize actions differently: not a student of that teacher"
        )
    demos = load_demos(args.demos, student.model.cfg.chunk_len)
    if args.samples > len(demos.actions):
        raise ValueError(f"--samples {args.samples}: the demonstrations hold {len(demos.actions)} steps")
    rows = np.random.default_rng(args.seed).choice(len(demos.actions), args.samples, replace=False)
    instructions = [demos.instructions[r] for r in rows]
    target = demos.actions[demos.chunk_index[rows]]  # (S, H, D)
    demo_tokens = student.tokenizer.encode(target).reshape(len(rows), -1)

    def run(text: str, ckpt: Any, path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, Any]:
        policy, params, pipelined = build(text, path)
        words, state = to_tensors(ckpt, instructions, demos.observations[rows][:, : ckpt.raw_state_dim])
        parts = [
            decode(policy, params, pipelined, words[b : b + args.batch], state[b : b + args.batch])
            for b in range(0, len(rows), args.batch)
        ]
        confs = [c for _, _, c in parts]
        return (
            np.concatenate([t for t, _, _ in parts]),
            np.concatenate([n for _, n, _ in parts]),
            None if confs[0] is None else np.concatenate(confs),
            params,
        )

    teacher_tokens, teacher_nfe, _, _ = run("bidirectional", teacher, args.teacher)
    table = [
        row_of(
            "bidirectional (teacher)",
            teacher_tokens,
            teacher_nfe,
            None,
            None,
            teacher_tokens,
            demo_tokens,
            target,
            student,
        )
    ]
    for setting in args.settings.split(";"):
        text = "fast_dvla" + (f":{setting}" if setting.strip() else "")
        tokens, nfe, conf, params = run(text, student, args.student)
        table.append(
            row_of(text, tokens, nfe, conf, params.tau_conf, teacher_tokens, demo_tokens, target, student)
        )
    return {
        "demos": args.demos,
        "student": args.student,
        "teacher": args.teacher,
        "samples": args.samples,
        "batch": args.batch,
        "seed": args.seed,
        "threads": args.threads,
        "machine": platform.platform(),
        "rows": table,
    }


def row_of(
    name: str,
    tokens: np.ndarray,
    nfe: np.ndarray,
    conf: np.ndarray | None,
    tau: float | None,
    teacher: np.ndarray,
    demo: np.ndarray,
    target: np.ndarray,
    ckpt: Any,
) -> dict[str, Any]:
    actions = ckpt.tokenizer.decode(tokens).reshape(target.shape)
    same = tokens == teacher
    row: dict[str, Any] = {
        "decoder": name,
        "nfe_per_chunk": float(nfe.mean()),
        "same_as_teacher": float(same.mean()),
        "same_as_demo": float((tokens == demo).mean()),
        "l1_to_demo": float(np.abs(actions - target).mean()),
        "below_tau_conf": None,
        "same_as_teacher_below": None,
        "same_as_teacher_at_or_above": None,
    }
    if conf is not None and tau is not None:
        below = conf < tau
        row["below_tau_conf"] = float(below.mean())
        row["same_as_teacher_below"] = float(same[below].mean()) if below.any() else None
        row["same_as_teacher_at_or_above"] = float(same[~below].mean()) if (~below).any() else None
    return row


def render(result: dict[str, Any]) -> str:
    def pct(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.1f}"

    lines = [
        "| decoder | NFE/chunk | below tau_conf % | = teacher % | = teacher, below % | = teacher, at/above % | = demo % | L1 to demo |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['decoder']} | {r['nfe_per_chunk']:.1f} | {pct(r['below_tau_conf'])} | {pct(r['same_as_teacher'])} "
            f"| {pct(r['same_as_teacher_below'])} | {pct(r['same_as_teacher_at_or_above'])} "
            f"| {pct(r['same_as_demo'])} | {r['l1_to_demo']:.4f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--demos", nargs="+", required=True, help="demonstrations folder(s) to draw states from"
    )
    parser.add_argument("--student", required=True, help="block-causal checkpoint decoded by fast_dvla")
    parser.add_argument("--teacher", required=True, help="bidirectional checkpoint, decoded at its defaults")
    parser.add_argument(
        "--settings",
        default="n=2;n=3;n=4;tau_add=1,tau_act=1",
        help="fast_dvla settings separated by ';', each as in --policy (empty: the defaults); "
        "tau_add=1,tau_act=1 decodes block after block (default: %(default)s)",
    )
    parser.add_argument(
        "--samples", type=int, default=512, help="demonstration steps drawn (default: %(default)s)"
    )
    parser.add_argument(
        "--batch", type=int, default=64, help="states decoded per batch (default: %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=0, help="which steps are drawn (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    parser.add_argument(
        "--json", default="benchmarks/results/commit-rule.json", help="where to write (default: %(default)s)"
    )
    args = parser.parse_args(argv)
    for flag, value in (("--samples", args.samples), ("--batch", args.batch), ("--threads", args.threads)):
        if value < 1:
            parser.error(f"{flag} must be at least 1, got {value}")
    try:
        result = measure(args)
    except (OSError, ValueError) as exc:  # a missing folder, a foreign checkpoint, a bad setting
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(render(result))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
