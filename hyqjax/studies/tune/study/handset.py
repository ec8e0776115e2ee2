"""Hand-set crawl configurations on a tuning study's held-out set: the comparison the tuner must win.

The equal-wall-clock study (:mod:`.wallclock`) evaluates Table I and its start point on its held-out set; a user's
alternative to tuning is any hand-set preset (:data:`hyqjax.crawl.presets.HAND_SET`: ``--remedy``, its options).
:func:`evaluate_presets` runs named presets on exactly the study's held-out instances (same seed, count, duration,
ranges and simulator), each as a member ``(parameterisation, theta_of(preset), preset)`` of the study's forward
program, and summarises each like a study member (:func:`.wallclock_results.summarize`: clean and completed success
with Wilson 95% intervals, per height, failure counts). :func:`best` names the preset with the highest clean rate.
"""
from __future__ import annotations

from hyqjax.crawl import presets


def check_study(res: dict) -> None:
    """Refuse a ``results.json`` without a held-out evaluation (one line)."""
    if res.get("kind") != "wallclock" or "heldout_set" not in res:
        raise ValueError("not an equal-wall-clock study with a held-out evaluation (run it to its held-out evaluation "
                         "first)")


def evaluate_presets(res: dict, names: list, done=None, log=print) -> dict:
    """Every preset in ``names`` on the held-out set of study ``res``: name -> summary; ``done(name, summary)`` after
    each (to store it)."""
    from hyqjax.studies.tune import forward, schedule
    from hyqjax.studies.tune.wallclock_config import WallClockConfig
    from hyqjax.studies.tune.wallclock_results import summarize

    check_study(res)
    cfg = WallClockConfig.from_dict(res["config"])
    param = schedule.make(cfg.dims[0], cfg.groups)
    bases = [presets.make(n) for n in names]
    sc, heights = forward.heldout_scenarios(cfg.heldout, cfg.heldout_seed)
    ev = forward.SuccessEvaluator(param, bases[0], cfg.heldout_duration, res.get("impl", cfg.impl))
    members = [(param, param.theta_of(b), b) for b in bases]
    out = {}

    def finished(i, cols):
        out[names[i]] = summarize(heights, cols)
        if done is not None:
            done(names[i], out[names[i]])

    forward.evaluate_sets(ev, members, sc, cfg.heldout_chunk, done=finished,
                          progress=lambda a, n, w: log(f"  hand-set {a}/{n} ({w:.1f} s)"))
    return out


def best(summaries: dict) -> tuple[str, dict]:
    """The preset with the highest held-out clean rate (ties: higher completed)."""
    name = max(summaries, key=lambda k: (summaries[k]["clean"], summaries[k]["completed"]))
    return name, summaries[name]


def table(summaries: dict, study: dict | None = None) -> str:
    """Markdown table of the presets (and of the study's own ``start`` and ``table1``, re-evaluated there)."""
    rows = ["| parameters | clean [95%] | completed [95%] | not completed | diverged |", "|---|---|---|---:|---:|"]
    fmt = lambda s, k: f"{s[k]:.3f} [{s[k + '_ci95'][0]:.3f}, {s[k + '_ci95'][1]:.3f}]"  # noqa: E731
    counts = lambda s: (f"{round(s['n'] * (1.0 - s['completed']))} | "  # noqa: E731
                        f"{s['failure_counts'].get('diverged', 0)}")
    for k in sorted(summaries, key=lambda k: -summaries[k]["clean"]):
        s = summaries[k]
        rows.append(f"| {k}: {presets.HAND_SET[k][1]} | {fmt(s, 'clean')} | {fmt(s, 'completed')} | {counts(s)} |")
    for k in ("start", "table1"):
        s = (study or {}).get("heldout", {}).get(k)
        if s:
            rows.append(f"| study's {k} | {fmt(s, 'clean')} | {fmt(s, 'completed')} | {counts(s)} |")
    return "\n".join(rows)


def check_names(names) -> list:
    bad = [n for n in names if n not in presets.HAND_SET]
    if bad or not names:
        raise ValueError(f"presets must be among {list(presets.HAND_SET)}, got {list(names)}")
    return list(dict.fromkeys(names))
