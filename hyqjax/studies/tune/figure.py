"""The study's figure: held-out clean success against simulation budget, and the gradient's statistics."""
from __future__ import annotations

import numpy as np

LABELS = {"gradient": "gradient (jacfwd, Adam + line search)", "cma_es": "CMA-ES (window objective)",
          "random_search": "random search (window objective)", "cma_es_success": "CMA-ES (success)",
          "random_search_success": "random search (success)"}


def plot_study(res: dict, path: str) -> str:
    """Left: held-out clean success (Wilson 95%) vs physics steps per method (budget-curve points and the
    final held-out evaluation), Table I (the paper's crawl) and the common start point as bands. Right: median gradient norm and mean SNR vs window length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.4))
    ho = res.get("heldout", {}).get("methods", {})
    budget = res["budget_physics_steps"]
    for key, color, label in (("table1", "0.8", "Table I, paper crawl"), ("start", "0.6", "start: Table I + remedy")):
        if key in ho:
            lo, hi = ho[key]["clean_ci95"]
            a1.axhspan(lo, hi, color=color, alpha=0.6, label=f"{label} ({ho[key]['clean']:.2f})")
    for i, m in enumerate(LABELS):
        pts = [(p["budget"], p["clean"], *p["clean_ci95"]) for p in res.get("budget_curve", []) if p["method"] == m]
        if m in ho:
            spent = res.get(m, {}).get("budget_spent", budget)
            pts.append((spent, ho[m]["clean"], *ho[m]["clean_ci95"]))
        if not pts:
            continue
        pts.sort()
        x, y, lo, hi = (np.asarray(v, float) for v in zip(*pts))
        a1.errorbar(x, y, yerr=[y - lo, hi - y], fmt="o-", color=f"C{i}", capsize=3, label=LABELS[m])
    a1.set_xlabel("simulation budget [physics steps, tangents counted]")
    a1.set_ylabel("held-out clean success")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    gs = res.get("gradient_stats")
    if gs:
        n = [p["ticks"] for p in gs["per_length"]]
        a2.semilogy(n, [p["median_norm"] for p in gs["per_length"]], "o-", label="median |grad| per window")
        a2.semilogy(n, [float(np.mean([np.nan if x is None else x for x in p["snr"]])) for p in gs["per_length"]], "s-",
                    label="mean SNR over parameters")
        a2.set_xlabel("window length [control ticks, 2 ms]")
        a2.grid(alpha=0.3)
        a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def summary_markdown(res: dict) -> str:
    """Markdown tables of a study's ``results.json``: held-out clean / completed success per method (Wilson
    95%), at 24 cm, largest heights; costs; gradient statistics per window length."""
    lines = []
    ho = res.get("heldout", {}).get("methods", {})
    if ho:
        lines += ["| method | budget (physics steps) | clean success [95%] | at 24 cm [95%] | completed [95%] | "
                  "shin strike | largest h, >= 90% completed | largest h, >= 95% clean |",
                  "|---|---:|---|---|---|---:|---:|---:|"]
        for m, r in ho.items():
            h24 = next((c for c in r["per_height"] if abs(c["height"] - 0.24) < 1e-6), None)
            spent = res.get(m, {}).get("budget_spent", res["budget_physics_steps"] if m == "gradient" else 0)
            f = lambda v, ci: f"{v:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"
            lines.append(f"| {m} | {spent:,} | {f(r['clean'], r['clean_ci95'])} | "
                         f"{f(h24['clean'], h24['clean_ci95']) if h24 else '-'} | "
                         f"{f(r['completed'], r['completed_ci95'])} | {r['shin_strike']:.3f} | "
                         f"{r['largest_h_completed_90']} | {r['largest_h_clean_95']} |")
        lines.append("")
    if "cost" in res:
        c = res["cost"]
        lines.append(f"one tuning step (jacfwd, {c['tangents']} tangents): {c['t_step_s']:.3f} s; "
                     f"{c['population']} forward evaluations of the same windows: {c['t_population_s']:.3f} s "
                     f"(step / forward = {c['step_over_forward']:.2f}); budget {res['budget_physics_steps']:,} steps")
    gs = res.get("gradient_stats")
    if gs:
        lines += ["", "| window (ticks) | median per-window norm | max norm | mean SNR | min / max SNR |",
                  "|---:|---:|---:|---:|---|"]
        for p in gs["per_length"]:
            snr = np.asarray([np.nan if x is None else x for x in p["snr"]], float)
            lines.append(f"| {p['ticks']} | {p['median_norm']:.3g} | {p['max_norm']:.3g} | {snr.mean():.2f} | "
                         f"{snr.min():.2f} / {snr.max():.2f} |")
    return "\n".join(lines)


def plot_wallclock(res: dict, path: str) -> str:
    """Budget curves of the equal-wall-clock study: held-out clean (top) and completed (bottom) success against
    wall-clock minutes (left) and physics steps (right), one colour per method and one line style per
    parameterisation; Table I and the start point as bands (Wilson 95%)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(13, 8.5), sharey="row")
    ho = res.get("heldout", {})
    methods = list(dict.fromkeys(c["method"] for c in res.get("budget_curves", [])))
    dims = list(dict.fromkeys(c["dim"] for c in res.get("budget_curves", [])))
    styles = ["-", "--", ":", "-."]
    for row, metric in enumerate(("clean", "completed")):
        for col, xkey in enumerate(("minutes", "physics_steps")):
            ax = axes[row, col]
            for key, color, label in (("table1", "0.85", "Table I, paper crawl"), ("start", "0.65", "start")):
                if key in ho:
                    lo, hi = ho[key][f"{metric}_ci95"]
                    ax.axhspan(lo, hi, color=color, alpha=0.6, label=f"{label} ({ho[key][metric]:.2f})")
            for c in res.get("budget_curves", []):
                pts = sorted(c["points"], key=lambda p: p[xkey])
                if not pts:
                    continue
                x = np.asarray([max(p[xkey], 1) for p in pts], float)
                y = np.asarray([p[metric] for p in pts])
                lo = np.asarray([p[f"{metric}_ci95"][0] for p in pts])
                hi = np.asarray([p[f"{metric}_ci95"][1] for p in pts])
                ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="o" + styles[dims.index(c["dim"]) % 4], capsize=2,
                            color=f"C{methods.index(c['method'])}", label=f"{c['method']} / {c['dim']} ({c['size']})")
            ax.set_xscale("log")
            ax.set_xlabel("wall-clock budget [min], compile included" if xkey == "minutes"
                          else "physics steps [tangents counted]")
            if col == 0:
                ax.set_ylabel(f"held-out {metric} success")
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"equal wall-clock tuning study, {res.get('device', '')}, impl {res.get('impl', '')}, "
                 f"{res.get('heldout_set', {}).get('instances', '?')} held-out instances", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def wallclock_markdown(res: dict) -> str:
    """Markdown table of the wall-clock study: held-out clean / completed [95%] per method, dim and checkpoint."""
    ho = res.get("heldout", {})
    minutes = res["config"]["wall_minutes"]
    f = lambda h, k: f"{h[k]:.3f} [{h[k + '_ci95'][0]:.3f}, {h[k + '_ci95'][1]:.3f}]"  # noqa: E731
    lines = ["| parameters | " + " | ".join(f"clean @ {m:g} min" for m in minutes) + " | completed @ "
             f"{minutes[-1]:g} min | physics steps | charged compile (s) |",
             "|---|" + "---|" * len(minutes) + "---|---:|---:|"]
    for key in ("table1", "start"):
        if key in ho:
            lines.append(f"| {key} | " + " | ".join(f(ho[key], "clean") for _ in minutes)
                         + f" | {f(ho[key], 'completed')} | – | – |")
    for c in res.get("budget_curves", []):
        r = res["runs"][f"{c['method']}/{c['dim']}"]
        by = {round(p["minutes"], 6): p for p in c["points"]}
        cells = [f(by[round(m, 6)], "clean") if round(m, 6) in by else "–" for m in minutes]
        last = by.get(round(minutes[-1], 6))
        lines.append(f"| {c['method']} / {c['dim']} ({c['size']}) | " + " | ".join(cells)
                     + f" | {f(last, 'completed') if last else '–'} | {r['physics_steps']:,} | {r['charged_s']:.1f} |")
    return "\n".join(lines)
