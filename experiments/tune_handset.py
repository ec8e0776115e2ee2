"""Hand-set crawl presets on a tuning study's held-out set (hyqjax.studies.tune.study.handset).

    python -m experiments.tune_handset DIR --presets start remedy remedy_fwd_0.10 adaptive remedy_all

DIR is a study directory with a held-out evaluation (``python -m experiments.tune_study --out DIR ...``); the presets
run on exactly its held-out instances and simulator. Prints every preset's clean and completed success with Wilson
95% intervals next to the study's own start point and Table I, names the best, and writes DIR/handset.json (kept
preset by preset: the same command skips the presets already there).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from hyqjax.crawl import presets

DEFAULT_PRESETS = ("start", "default", "remedy", "remedy_fwd_0.10", "remedy_lower_0.05", "adaptive", "remedy_all")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.tune_handset", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", help="a tuning study directory with its held-out evaluation")
    p.add_argument("--presets", nargs="+", default=list(DEFAULT_PRESETS),
                   help=f"hand-set presets (hyqjax.crawl.presets): {', '.join(presets.HAND_SET)}")
    args = p.parse_args(argv)
    from hyqjax.studies.tune.study import handset

    try:
        names = handset.check_names(args.presets)
        with open(os.path.join(args.dir, "results.json")) as f:
            res = json.load(f)
        handset.check_study(res)
    except (OSError, ValueError) as e:
        print(f"tune_handset: {e}", file=sys.stderr)
        return 2
    path = os.path.join(args.dir, "handset.json")
    have = {}
    if os.path.exists(path):
        with open(path) as f:
            prev = json.load(f)
        if prev.get("heldout_set") == res["heldout_set"]:
            have = prev.get("presets", {})
    from hyqjax.io import atomic

    out = dict(heldout_set=res["heldout_set"], presets=dict(have))

    def done(name, summary):
        out["presets"][name] = summary
        atomic.write_json(path, out)

    todo = [n for n in names if n not in have]
    if todo:
        handset.evaluate_presets(res, todo, done=done)
    shown = {k: out["presets"][k] for k in names}
    print(handset.table(shown, res))
    name, s = handset.best(shown)
    print(f"best hand-set preset: {name}, clean {s['clean']:.3f} [{s['clean_ci95'][0]:.3f}, {s['clean_ci95'][1]:.3f}]")
    out["best"] = name
    atomic.write_json(path, out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
