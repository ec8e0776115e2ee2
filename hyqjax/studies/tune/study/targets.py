"""The default tuner's targets, judged over repeated runs on one held-out reach map.

A *run* is one ``hyqjax tune`` with its defaults (one training seed); the sets the runs return and some reference
presets are evaluated on the same held-out instances (``python -m experiments.reach_map`` on the wide spread, a
seed and heights no part of the tuner saw: :data:`HELDOUT`). Per variant (a run's set or a reference):

* ``clean``: clean success pooled over the heights up to :data:`CLEAN_MAX_HEIGHT` (Wilson 95% interval);
* ``per_height``: clean success at every height, and ``worst_low``: the lowest clean rate at the heights up to
  :data:`PER_HEIGHT_MAX` (with its height);
* ``h90``: the tallest height with >= 90 % completed step-downs there and at every lower height (the reach map's);
* ``far_start``: clean success up to :data:`CLEAN_MAX_HEIGHT` in the last third of the spread's start distances
  (10-15 cm before the edge on the wide spread; the training spread draws 0-10 cm).

Over the runs: the mean of ``clean`` with the 95% Student-t interval over runs (:func:`.repeats.over_runs`), the
range (max - min), and the issue's four targets, each ``pass`` / ``fail`` with the measured value:

* ``clean_lower``: the lower end of the interval over runs >= :data:`CLEAN_LOWER` (0.80);
* ``per_height``: every run >= :data:`PER_HEIGHT_CLEAN` (0.85) at every height up to 24 cm;
* ``h90``: every run's ``h90`` >= :data:`H90` (27 cm);
* ``spread``: the range of ``clean`` over runs <= :data:`SPREAD` (0.05).

With runs that recorded checkpoints before the end of their budget (``hyqjax tune``'s default records 3, 10 and 30
minutes), the iterate each run held at each earlier checkpoint runs on the same map as ``<run>@<minutes>min``
(:func:`checkpoint_variant`), and ``budgets`` gives per budget the mean clean success over the runs with its
t-interval and range: what a user gets at 3, 10 and 30 minutes (the last is the returned set). ``budget_gains``
compares each budget with every shorter one, paired run by run (the same run's clean success at the longer budget
minus at the shorter, over the runs that have both), and, where the runs' start point is one of the references
(``start``), each budget with the start on the same step-downs: the mean gain with its t-interval over runs, and
``more`` (the interval above 0: the longer budget returns more), ``less`` (below 0) or ``tie``. A longer default
budget is worth its minutes only where it is ``more``.
"""
from __future__ import annotations

from hyqjax.studies import statistics
from hyqjax.studies.tune.study.repeats import over_runs

#: The held-out reach map of the targets: the wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm),
#: heights of which none is a training height (the tuner trains at 16, 20, 24 and 28 cm) and a seed no study used.
HELDOUT = dict(spread="wide", seed=60613, instances=512,
               heights=(0.14, 0.15, 0.17, 0.18, 0.19, 0.21, 0.22, 0.23, 0.25, 0.26, 0.27, 0.29))
CLEAN_MAX_HEIGHT = 0.26
PER_HEIGHT_MAX = 0.24
CLEAN_LOWER = 0.80
PER_HEIGHT_CLEAN = 0.85
H90 = 0.27
SPREAD = 0.05


def variant_summary(cell: dict) -> dict:
    """One reach-map cell (a variant on one spread) -> its ``clean``, ``per_height``, ``worst_low``, ``h90``,
    ``diverged`` and ``n``."""
    rows = sorted(cell["per_height"], key=lambda r: r["height"])
    low = [r for r in rows if r["height"] <= CLEAN_MAX_HEIGHT + 1e-9]
    k, n = sum(r["clean"] for r in low), sum(r["n"] for r in low)
    lo, hi = statistics.wilson_interval(int(k), int(n))
    upto = [r for r in rows if r["height"] <= PER_HEIGHT_MAX + 1e-9]
    worst = min(upto, key=lambda r: r["clean_rate"]) if upto else None
    far = [r["by_factor"]["start_distance"][-1] for r in low if "by_factor" in r]
    kf, nf = sum(p["n"] * (p["clean"] or 0.0) for p in far), sum(p["n"] for p in far)
    return dict(clean=k / n if n else None, clean_ci95=[lo, hi], n_clean=int(n),
                far_start=dict(clean=kf / nf if nf else None, n=int(nf),
                               range=far[0]["range"] if far else None),
                per_height=[dict(height=r["height"], clean=r["clean_rate"], completed=r["completed_rate"],
                                 n=r["n"]) for r in rows],
                worst_low=None if worst is None else dict(height=worst["height"], clean=worst["clean_rate"]),
                h90=cell.get("h90"), diverged=int(cell.get("diverged", 0)), n=int(cell.get("n", 0)))


def checkpoint_variant(run: str, minutes: float) -> str:
    """The reach-map variant of the iterate run ``run`` held at its checkpoint of ``minutes``."""
    return f"{run}@{minutes:g}min"


def judge(cells: list[dict], runs: list[str], references: list[str] = (), seed: int | None = None,
          budgets: dict | None = None, start: str | None = None) -> dict:
    """The targets over ``runs`` (variant names of the reach map ``cells``), with ``references`` summarised beside
    them; ``seed`` is the map's draw seed (default :data:`HELDOUT`'s). ``budgets`` maps minutes to the variants of
    the runs at that budget (:func:`checkpoint_variant`; the end of the budget: ``runs``), summarised over runs
    as ``budgets``; ``start``: the reference every run started from, against which each budget's gain is paired
    (:func:`budget_gains`). A run, reference or checkpoint variant missing from the map is a ``ValueError`` naming
    it, as is a ``start`` that is not one of the ``references``."""
    if start is not None and start not in references:
        raise ValueError(f"the start {start} is not one of the references ({', '.join(references) or 'none'})")
    by = {c["variant"]: c for c in cells if c.get("spread", HELDOUT["spread"]) == HELDOUT["spread"]}
    extra = [v for vs in (budgets or {}).values() for v in vs if v not in runs]
    missing = [v for v in list(runs) + list(references) + extra if v not in by]
    if missing:
        raise ValueError(f"variant {missing[0]} is not in the reach map (it has {', '.join(sorted(by))})")
    per = {v: variant_summary(by[v]) for v in list(runs) + list(references) + extra}
    clean = [per[v]["clean"] for v in runs]
    stats = over_runs(clean)
    rng = float(max(clean) - min(clean)) if runs else None
    worst = min((per[v]["worst_low"]["clean"] for v in runs if per[v]["worst_low"]), default=None)
    h90s = [per[v]["h90"] for v in runs]
    lower = stats["ci95"][0] if stats.get("ci95") else None
    targets = dict(
        clean_lower=dict(value=lower, target=CLEAN_LOWER, ok=lower is not None and lower >= CLEAN_LOWER),
        per_height=dict(value=worst, target=PER_HEIGHT_CLEAN, ok=worst is not None and worst >= PER_HEIGHT_CLEAN),
        h90=dict(value=min((h for h in h90s if h is not None), default=None) if all(h is not None for h in h90s)
                 else None, target=H90, ok=bool(runs) and all(h is not None and h >= H90 - 1e-9 for h in h90s)),
        spread=dict(value=rng, target=SPREAD, ok=rng is not None and rng <= SPREAD))
    curve = []
    for minutes, names in sorted((budgets or {}).items(), key=lambda kv: float(kv[0])):
        c = [per[v]["clean"] for v in names]
        curve.append(dict(minutes=float(minutes), variants=list(names), clean=c,
                          range=float(max(c) - min(c)) if c else None,
                          **over_runs(c)))
    return dict(heldout=dict(HELDOUT, **map_layout(by[runs[0]] if runs else None),
                             seed=HELDOUT["seed"] if seed is None else int(seed),
                             clean_max_height=CLEAN_MAX_HEIGHT, per_height_max=PER_HEIGHT_MAX),
                runs=list(runs), references=list(references), variants=per,
                over_runs=dict(stats, range=rng, clean=clean), targets=targets, budgets=curve,
                budget_gains=budget_gains(curve, dict(name=start, clean=per[start]["clean"]) if start else None),
                diverged=sum(per[v]["diverged"] for v in per))


def map_layout(cell: dict | None) -> dict:
    """The instances per height and the heights a reach map's ``cell`` ran (empty for none): a map made with other
    ``--instances`` or ``--heights`` than :data:`HELDOUT`'s is reported as it ran."""
    rows = (cell or {}).get("per_height") or []
    if not rows:
        return {}
    return dict(instances=int(max(r["n"] for r in rows)), heights=tuple(float(r["height"]) for r in rows))


def budget_gains(curve: list[dict], start: dict | None = None) -> list[dict]:
    """Each budget of ``curve`` (:func:`judge`'s ``budgets``, shortest first) against every shorter one, paired by
    run (module docstring), and, with ``start`` (``{"name": reference, "clean": its clean success}``), against the
    start point on the same step-downs (``from`` 0 minutes, ``start`` its name), these first: ``from``/``to``
    minutes, the runs paired, each run's gain, the mean gain, its 95% t-interval over runs and the verdict
    ``more`` / ``less`` / ``tie``."""
    from hyqjax.studies.tune.tuned import split_checkpoint  # the one parser of NAME@Nmin

    def run_of(variant: str) -> str:  # run_0@10min (checkpoint_variant) -> run_0
        return split_checkpoint(variant)[0]

    def gain(pairs, **where):
        gains = [g for _, g in pairs]
        stats = over_runs(gains)
        ci = stats.get("ci95")
        verdict = None if ci is None else "more" if ci[0] > 0 else "less" if ci[1] < 0 else "tie"
        return dict(stats, **where, runs=[r for r, _ in pairs], gain=gains, verdict=verdict)

    out = []
    if start is not None:
        out += [gain([(run_of(v), c - start["clean"]) for v, c in zip(b["variants"], b["clean"])],
                     **{"from": 0.0, "to": b["minutes"], "start": start["name"]}) for b in curve]
    for j, b in enumerate(curve):
        for a in curve[:j]:
            before = {run_of(v): c for v, c in zip(a["variants"], a["clean"])}
            out.append(gain([(run_of(v), c - before[run_of(v)]) for v, c in zip(b["variants"], b["clean"])
                             if run_of(v) in before], **{"from": a["minutes"], "to": b["minutes"]}))
    return sorted(out, key=lambda g: ("start" not in g, g["to"] - g["from"], g["from"]))


def table(summary: dict) -> str:
    """Markdown: one row per run and reference, then the targets."""
    def f(x, d=3):
        return "-" if x is None else f"{x:.{d}f}"

    def cm(h):
        return "-" if h is None else f"{100 * h:.0f} cm"

    returned = summary.get("returned", {})
    lines = ["| set | clean (<= {:.0f} cm) [95%] | worst clean <= {:.0f} cm (height) | h90 | clean at the farthest "
             "starts | diverged | returned iterate: validation / pooled clean |".format(
                 100 * CLEAN_MAX_HEIGHT, 100 * PER_HEIGHT_MAX), "|---|---|---|---|---|---|---|"]
    for v in summary["runs"] + summary["references"]:
        s = summary["variants"][v]
        w = s["worst_low"]
        far = s.get("far_start") or {}
        r = returned.get(v)
        it = "" if not r else f"{r['iteration']}: {f(r['validation_clean'])} / {f(r['pooled_clean'])}"
        lines.append(f"| {v} | {f(s['clean'])} [{f(s['clean_ci95'][0])}, {f(s['clean_ci95'][1])}] | "
                     f"{f(w and w['clean'])} ({cm(w and w['height'])}) | {cm(s['h90'])} | "
                     f"{f(far.get('clean'), 2)} | {s['diverged']} | {it} |")
    o = summary["over_runs"]
    ci = o.get("ci95")
    lines += ["", f"over {o['n']} runs: clean {f(o['mean'])}"
              + (f" [{f(ci[0])}, {f(ci[1])}] (95% t-interval over runs)" if ci else "")
              + f", range {f(o['range'])}", "", "| target | measured | required | met |", "|---|---|---|---|"]
    t = summary["targets"]
    rows = [("clean, lower end of the interval over runs", f(t["clean_lower"]["value"]), f">= {CLEAN_LOWER:.2f}",
             t["clean_lower"]["ok"]),
            (f"clean at every height <= {100 * PER_HEIGHT_MAX:.0f} cm (worst run and height)",
             f(t["per_height"]["value"]), f">= {PER_HEIGHT_CLEAN:.2f}", t["per_height"]["ok"]),
            ("h90 on the wide spread (lowest run)", cm(t["h90"]["value"]), f">= {cm(H90)}", t["h90"]["ok"]),
            ("range of clean over runs", f(t["spread"]["value"]), f"<= {SPREAD:.2f}", t["spread"]["ok"])]
    lines += [f"| {a} | {b} | {c} | {'yes' if ok else 'no'} |" for a, b, c, ok in rows]
    if summary.get("budgets"):
        head = f"| budget | runs | clean (<= {100 * CLEAN_MAX_HEIGHT:.0f} cm) over runs [95%] | range | per run |"
        lines += ["", head, "|---|---|---|---|---|"]
        for b in summary["budgets"]:
            ci = b.get("ci95")
            lines.append(f"| {b['minutes']:g} min | {b['n']} | {f(b['mean'])}"
                         + (f" [{f(ci[0])}, {f(ci[1])}]" if ci else "") + f" | {f(b['range'])} | "
                         + " / ".join(f(c) for c in b["clean"]) + " |")
    if summary.get("budget_gains"):
        lines += ["", "| longer budget | runs paired | gain in clean over runs [95%] | verdict | per run |",
                  "|---|---|---|---|---|"]
        for g in summary["budget_gains"]:
            ci = g.get("ci95")
            frm = f"the start ({g['start']})" if g.get("start") else f"{g['from']:g}"
            lines.append(f"| {frm} -> {g['to']:g} min | {g['n']} | "
                         + ("-" if g["mean"] is None else f"{g['mean']:+.3f}")
                         + (f" [{ci[0]:+.3f}, {ci[1]:+.3f}]" if ci else "") + f" | {g['verdict'] or '-'} | "
                         + " / ".join(f"{x:+.3f}" for x in g["gain"]) + " |")
    return "\n".join(lines)


def reach_map_arguments(runs: dict, references=(), extra_runs=(), impl: str = "auto", out: str = "",
                        instances: int | None = None, seed: int | None = None,
                        checkpoints: dict | None = None) -> list[str]:
    """``python -m experiments.reach_map`` arguments of the targets' held-out map: ``runs`` maps a variant name to
    a tuning ``results.json`` (its one run), ``references`` are presets, ``extra_runs`` further
    ``NAME:PATH:METHOD[:settings]`` variants; ``seed`` draws the map's instances (default :data:`HELDOUT`'s);
    ``checkpoints`` maps a run's variant name to the minutes of its earlier checkpoints, each a further variant
    (:func:`checkpoint_variant`: the iterate the run held there)."""
    h = HELDOUT
    argv = ["--out", out, "--impl", impl, "--instances", str(instances or h["instances"]), "--spread", h["spread"],
            "--seed", str(h["seed"] if seed is None else seed), "--heights", *[f"{x:g}" for x in h["heights"]]]
    if references:
        argv += ["--preset", *references]
    at = []
    for name, path in runs.items():
        key = _only_run(path)
        argv += ["--tuned-run", f"{name}:{path}:{key}"]
        for m in (checkpoints or {}).get(name, ()):
            at.append(checkpoint_variant(name, m))
            argv += ["--tuned-run", f"{at[-1]}:{path}:{key}@{m:g}min"]
    for t in extra_runs:
        argv += ["--tuned-run", t]
    names = list(references) + list(runs) + at + [t.split(":", 1)[0] for t in extra_runs]
    return argv + ["--variants", *names]


def _only_run(path: str) -> str:
    from hyqjax.studies.tune import tuned

    return tuned.pick_run(tuned.read(path), None, path)

