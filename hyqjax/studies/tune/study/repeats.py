"""Repeated runs of the equal-wall-clock study: how much one method's result varies from run to run, and which
methods are apart once that is counted.

One run of a method gives one held-out clean rate with a Wilson interval over the held-out instances; a second
run of the same method (another ``--seed``, or the same seed on MuJoCo Warp, whose batched results are not bitwise
reproducible) returns other parameters, and on 68 coordinates two such runs differed by 0.09 (docs/tuning.md),
more than the methods did. The interval that ranks methods is therefore the one over runs:

* for each (method, parameterisation) and budget, the held-out clean (and completed) rate of every run, their mean
  ``m`` and sample standard deviation ``s`` over the ``n`` runs, and the 95% Student-t interval of the mean,
  ``m +- t_{0.975, n-1} s / sqrt(n)`` (none for one run);
* a method is *apart* from another when its interval over runs lies entirely above the other's.

Every run must be a study directory of one configuration but for its seed (``config.seed``) and methods, on the
same held-out set (``heldout_set``); anything else is refused naming the first setting that differs. A setting only
some methods read (the surrogate's windows, a method's own rates) need agree only between runs that both ran such a
method.
``python -m experiments.tune_repeats DIR [DIR ...] --minutes 10`` prints the table and writes JSON.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np

#: Settings that may differ between the runs of one comparison.
FREE_SETTINGS = ("seed", "methods")


def load(directory: str) -> dict:
    """``results.json`` of a study directory, or a study's results file given by its path (a ``ValueError`` naming
    it if it has none)."""
    path = directory if os.path.isfile(directory) else os.path.join(directory, "results.json")
    try:
        with open(path) as f:
            res = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{directory}: no readable results.json ({e})") from None
    if res.get("kind") != "wallclock":
        raise ValueError(f"{directory}: results.json is not an equal-wall-clock study")
    return res


def _settings(config: dict, free=FREE_SETTINGS) -> dict:
    """A run's settings but the ``free`` ones; a setting its study predates counts at its default (the behaviour
    the run had)."""
    from hyqjax.studies.tune.wallclock_config import WallClockConfig

    out = {k: v for k, v in WallClockConfig.defaults().items() if k not in config}
    out.update(config)
    return {k: v for k, v in out.items() if k not in free}


def check_comparable(results: list[dict], names: list[str], free=FREE_SETTINGS, methods=None) -> None:
    """Refuse runs of different configurations (but for the ``free`` settings: by default their seed and methods)
    or held-out sets, each run checked against every one before it. ``methods``: per run, the methods judged of it
    (default: every method it ran); a setting only some methods read
    (:data:`hyqjax.studies.tune.wallclock_config.SETTING_READERS`) is compared only between runs that both judge
    a method reading it."""
    from hyqjax.studies.tune.wallclock_config import SETTING_READERS

    judged = [set(m if m is not None else r["config"].get("methods", ()))
              for r, m in zip(results, methods or [None] * len(results))]
    settings = [_settings(r["config"], free) for r in results]
    for j in range(1, len(results)):
        for i in range(j):
            for k in sorted(set(settings[i]) | set(settings[j])):
                readers = SETTING_READERS.get(k)
                if readers is not None and not (judged[i] & set(readers) and judged[j] & set(readers)):
                    continue
                if settings[i].get(k) != settings[j].get(k):
                    raise ValueError(f"{names[j]} differs from {names[i]} in {k}: {settings[j].get(k)!r} against "
                                     f"{settings[i].get(k)!r}")
            if results[j].get("heldout_set") != results[i].get("heldout_set"):
                raise ValueError(f"{names[j]} was evaluated on another held-out set than {names[i]}")


def t_quantile(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` degrees of freedom."""
    from scipy import stats

    return float(stats.t.ppf(0.975, df))


def over_runs(values: list[float]) -> dict:
    """Mean, sample standard deviation and the 95% t-interval of the mean of one value per run (no runs: all None)."""
    v = np.asarray(values, np.float64)
    n = int(v.size)
    if n == 0:
        return dict(n=0, mean=None, sd=None, ci95=None)
    mean = float(v.mean())
    if n < 2:
        return dict(n=n, mean=mean, sd=None, ci95=None)
    sd = float(v.std(ddof=1))
    half = t_quantile(n - 1) * sd / math.sqrt(n)
    return dict(n=n, mean=mean, sd=sd, ci95=[mean - half, mean + half])


def collect(results: list[dict], names: list[str], minutes: float) -> dict:
    """Per member (``method/dim``, and ``start``, ``table1``): the held-out clean and completed rate of every run
    at ``minutes`` (with the run's name and seed) and :func:`over_runs` of both."""
    check_comparable(results, names)
    from hyqjax.studies.tune.wallclock_results import member_key

    rows: dict[str, list] = {}
    for res, name in zip(results, names):
        seed = res["config"].get("seed")
        for key, run in res.get("runs", {}).items():
            h = res["heldout"].get(member_key(run["method"], run["dim"], minutes * 60.0))
            if h is not None:
                rows.setdefault(key, []).append(dict(run=name, seed=seed, clean=h["clean"], completed=h["completed"],
                                                     clean_ci95=h["clean_ci95"], n=h["n"]))
        for ref in ("start", "table1"):
            if ref in res["heldout"]:
                h = res["heldout"][ref]
                rows.setdefault(ref, []).append(dict(run=name, seed=seed, clean=h["clean"], completed=h["completed"],
                                                     clean_ci95=h["clean_ci95"], n=h["n"]))
    out = {}
    for key, runs in rows.items():
        out[key] = dict(runs=runs, clean=over_runs([r["clean"] for r in runs]),
                        completed=over_runs([r["completed"] for r in runs]))
    for key, row in out.items():
        ci = row["clean"]["ci95"]
        row["apart_from"] = sorted(k for k, o in out.items() if k != key and ci is not None
                                   and o["clean"]["ci95"] is not None and ci[0] > o["clean"]["ci95"][1])
    return out


def difference(a: list[float], b: list[float]) -> dict | None:
    """The difference of two members' mean clean rates over runs, ``m_a - m_b``, with Welch's 95% interval
    ``(m_a - m_b) +- t_{0.975, nu} sqrt(s_a^2 / n_a + s_b^2 / n_b)`` (Welch-Satterthwaite ``nu``) and the two-sided
    p-value of Welch's t-test (``scipy.stats.ttest_ind``, ``equal_var=False``); None with fewer than 2 runs of
    either or no spread in both. A weaker claim than :func:`collect`'s ``apart_from`` (two intervals over runs
    that do not overlap), which is what the study's targets ask for."""
    from scipy import stats

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.size < 2 or b.size < 2:
        return None
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    if va + vb == 0.0:
        return None
    nu = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    d = float(a.mean() - b.mean())
    half = float(stats.t.ppf(0.975, nu)) * math.sqrt(va + vb)
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    return dict(mean=d, ci95=[d - half, d + half], df=float(nu), p_two_sided=p)


def differences(summary: dict) -> dict:
    """:func:`difference` of every ordered pair of tuned members (``method/dim``), the higher mean first."""
    keys = sorted((k for k in summary if "/" in k), key=lambda k: -summary[k]["clean"]["mean"])
    out = {}
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            d = difference([r["clean"] for r in summary[a]["runs"]], [r["clean"] for r in summary[b]["runs"]])
            if d is not None:
                out[f"{a} - {b}"] = d
    return out


def table(summary: dict, minutes: float) -> str:
    """A markdown table of :func:`collect`'s summary, best mean clean first."""
    lines = [f"held-out clean success at {minutes:g} min over runs (95% t-interval of the mean over runs)", "",
             "| member | runs | clean per run | clean: mean [95% over runs] | sd | completed: mean | apart from |",
             "|---|---:|---|---|---:|---:|---|"]
    for key, row in sorted(summary.items(), key=lambda kv: -kv[1]["clean"]["mean"]):
        c = row["clean"]
        ci = "–" if c["ci95"] is None else f"[{c['ci95'][0]:.3f}, {c['ci95'][1]:.3f}]"
        sd = "–" if c["sd"] is None else f"{c['sd']:.3f}"
        per = ", ".join(f"{r['clean']:.3f}" for r in row["runs"])
        lines.append(f"| {key} | {c['n']} | {per} | {c['mean']:.3f} {ci} | {sd} | {row['completed']['mean']:.3f} | "
                     f"{', '.join(row['apart_from']) or '–'} |")
    diffs = differences(summary)
    if diffs:
        lines += ["", "difference of means over runs (Welch's 95% interval; weaker than 'apart from')", "",
                  "| difference | mean [95% Welch] | df | p (two-sided) |", "|---|---|---:|---:|"]
        for k, d in diffs.items():
            lines.append(f"| {k} | {d['mean']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] | {d['df']:.1f} | "
                         f"{d['p_two_sided']:.3f} |")
    return "\n".join(lines)
