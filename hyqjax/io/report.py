"""A results report people can read: one self-contained HTML page built from experiment output directories.

:func:`build_report` looks for ``results.json`` (``hyqjax stepdown`` / ``bound``) and ``summary.json``
(``hyqjax sweep``) in a directory and in its subdirectories, and writes one section per experiment
it finds:

* the exact command, seed, date, versions and devices (``results.json["provenance"]``) and the
  experiment's options (``config`` / ``args``);
* step-down (``summary`` + ``instances``): the paper's table, success rate per height and reflex
  setting with its Wilson 95% interval, and the failed instances with their reasons;
* bounding (``groups``): tracking, fall and periodicity numbers per configuration and, for an
  ablation, each part's contribution;
* sweep (``summary.json``): instances run and planned, completed and clean runs per reflex setting with
  the largest safe height (``h95``) of each, both against height, and the failure reasons;
* every PNG figure of the directory (success maps, the paper's figures, bounding tracking plots),
  and the stills and videos ``hyqjax render`` wrote to ``DIR/render/``.

Images are embedded as data URIs so the page is one file that can be mailed or attached to a
results log; videos are embedded up to a size limit and linked otherwise. Unknown result files are
tolerated: what is recognised is shown, the rest is listed by key.
"""
from __future__ import annotations

import base64
import datetime
import html
import json
import math
import os
from typing import Any, Iterable

RESULTS_FILE = "results.json"
SWEEP_FILE = "summary.json"
RENDER_DIR = "render"
#: Captions of the figures hyqjax writes (others are shown with their file name).
CAPTIONS = {
    "success.png": ("Step-down clean success rate (completed and no shin strike) per platform height, reflex off / "
                    "on, with 95% Wilson intervals."),
    "fig9_reflex.png": "Height reflex stepping down (cf. Fig. 9): activation, damping vs. swing mobility, feet.",
    "fig10_end_stop.png": "Joint trajectories at the end stop (cf. Fig. 10).",
    "fig11_pitch.png": "Trunk pitch while stepping down, per height and reflex setting (cf. Fig. 11).",
    "yaw_tracking.png": "Bounding: desired vs. actual heading (cf. Orsolino et al., Fig. 4).",
    "speed_tracking.png": "Bounding: desired vs. actual forward speed.",
    "success_maps.png": "Sweep: completed and clean probability maps per reflex setting.",
    "success_height.png": "Sweep: completed and clean probability vs. step height with 95% Wilson intervals.",
}
MIME = {".png": "image/png", ".gif": "image/gif", ".mp4": "video/mp4"}
STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1100px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}h3{margin-top:1.5em}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}td,th{border:1px solid #ddd;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}code,pre{background:#f6f6f6;padding:.1em .3em}
pre{padding:.6em;overflow-x:auto}figure{margin:1em 0}figure img,figure video{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}.stills{display:flex;flex-wrap:wrap;gap:.5em}.stills figure{margin:0;
flex:1 1 300px}.fail{color:#b00}.ok{color:#070}
"""


def find_result_dirs(root: str, max_depth: int = 3) -> list[str]:
    """``root`` (if it holds results.json or a sweep's summary.json) and every subdirectory down to ``max_depth``
    that does, sorted."""
    found = []
    root = os.path.abspath(root)
    for dirpath, dirnames, filenames in os.walk(root):
        depth = os.path.relpath(dirpath, root).count(os.sep) + (dirpath != root)
        if depth >= max_depth:
            dirnames[:] = []
        dirnames.sort()
        if RESULTS_FILE in filenames or SWEEP_FILE in filenames:
            found.append(dirpath)
    return sorted(found, key=lambda p: (p != root, p))


def load_results(directory: str) -> dict[str, Any]:
    """results.json of ``directory``, else its sweep summary.json (marked with ``_sweep``)."""
    path = os.path.join(directory, RESULTS_FILE)
    if os.path.isfile(path):
        with open(path) as f:
            return json.load(f)
    with open(os.path.join(directory, SWEEP_FILE)) as f:
        return {**json.load(f), "_sweep": True}


def esc(x: Any) -> str:
    return html.escape(str(x))


def fmt(v: Any, spec: str = "{:.3f}") -> str:
    """A number for a table cell (``-`` for missing / NaN), booleans as on/off."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            return "-"
        return spec.format(v) if isinstance(v, float) else str(v)
    return esc(v)


def table(headers: list[str], rows: Iterable[list[str]], left: int = 0) -> str:
    """An HTML table; the first ``left`` columns are left-aligned. Cells are already escaped."""
    th = "".join(f'<th class="{"l" if i < left else ""}">{esc(h)}</th>' for i, h in enumerate(headers))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
                   + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def data_uri(path: str) -> str:
    with open(path, "rb") as f:
        data = base64.b64encode(f.read()).decode("ascii")
    return f"data:{MIME[os.path.splitext(path)[1].lower()]};base64,{data}"


def provenance_html(res: dict) -> str:
    p = res.get("provenance") or {}
    if not p:
        return "<p><em>No provenance recorded.</em></p>"
    cmd = f"<p>Command: <code>{esc(p.get('command', '?'))}</code></p>"
    keys = [k for k in ("seed", "date", "hyqjax", "jax", "mujoco", "mujoco_mjx", "python") if k in p]
    rows = [[esc(k), esc(p[k])] for k in keys]
    if p.get("devices"):
        rows.append(["devices", esc(", ".join(map(str, p["devices"])))])
    if "wall_time_s" in res:
        rows.append(["wall time", f"{fmt(res['wall_time_s'], '{:.1f}')} s"])
    clock = res.get("phases") or res.get("phases_this_run")
    if isinstance(clock, dict) and isinstance(clock.get("phases"), dict):  # hyqjax.io.phases.Clock.to_dict
        from hyqjax.io.phases import LABELS

        parts = [f"{LABELS.get(k, k)} {fmt(v, '{:.1f}')} s" for k, v in clock["phases"].items()]
        rows.append(["wall time by phase", esc(", ".join(parts))])
    if "env_steps_per_s" in res:
        rows.append(["env-steps/s", fmt(res["env_steps_per_s"], "{:,.0f}")])
    return cmd + table(["", "value"], rows, left=2)


def options_html(res: dict) -> str:
    opts = res.get("config") or res.get("args") or {}
    opts = {k: v for k, v in opts.items() if not k.startswith("_") and v is not None}
    if not opts:
        return ""
    items = " ".join(f"<code>{esc(k)}={esc(json.dumps(v))}</code>" for k, v in sorted(opts.items()))
    return f"<p>Options: {items}</p>"


def _reasons(row: dict) -> str:
    """The failure reasons of an instance row: its boolean reason columns (a legacy ``failure_reason`` text)."""
    from hyqjax.studies.stepdown_outcome import failure_labels

    return ", ".join(failure_labels(row)) or str(row.get("failure_reason", ""))


def _reason_counts(reasons) -> str:
    """``feet_not_down 2, shin_strike 1`` of a ``{reason: runs}`` mapping (``-`` for none, ``n/a`` if absent)."""
    if reasons is None:
        return "n/a"
    return ", ".join(f"{k} {v}" for k, v in reasons.items()) or "-"


def stepdown_html(res: dict) -> str:
    """The step-down table (one row per height and reflex setting: completed and clean runs with Wilson 95%
    intervals) and the list of failed instances."""
    rows = []
    for r in res.get("summary") or []:
        cells = []
        for key in ("completed", "clean"):
            old = "success" if key == "clean" and key not in r else key  # results written before the hierarchy
            ci = r.get(f"{old}_ci95") or [None, None]
            rate = r.get(f"{old}_rate")
            k = r.get(key, r.get("successes", "?") if old == "success" else "?")
            cells += [f"{k}/{r.get('n', '?')}" + (f" ({rate:.0%})" if isinstance(rate, float) else ""),
                      f"[{fmt(ci[0], '{:.2f}')}, {fmt(ci[1], '{:.2f}')}]"]
        rows.append([fmt(r.get("height"), "{:.2f}"), fmt(r.get("reflex")), *cells,
                     fmt(r.get("lost_foothold_share"), "{:.0%}"), fmt(r.get("joint_past_range"), "{:.0%}"),
                     fmt(r.get("shin_strike"), "{:.0%}"),
                     fmt(r.get("min_swing_mobility")), fmt(r.get("mean_mobility")), fmt(r.get("peak_pitch")),
                     fmt(r.get("time_all_down"), "{:.1f}"), fmt(r.get("diverged")),
                     esc(_reason_counts(r.get("failure_reasons")))])
    out = "<h3>Step-down results</h3>"
    out += table(["height [m]", "reflex", "completed", "95% CI", "clean", "95% CI", "runs losing a foothold",
                  "runs with a joint past its range", "runs with a shin strike",
                  "min m_sw", "mean m", "peak pitch [rad]", "t all down [s]", "diverged",
                  "failure reasons (runs)"], rows)
    out += ("<p>completed: all four feet on the lower ground, forward progress, no lost foothold, no joint past its "
            "range, no trunk strike, |roll| and |pitch| bounded, no reflex failure, finite; clean: completed and no "
            "shin contact above 100 N. m_sw: velocity transformation ratio of the swing leg while it moves down "
            "(Eq. 12); mean m: overall mobility per swing-down tick; failure reasons: runs per reason among the "
            "runs that are not clean (a run can have several).</p>")
    inst = res.get("instances") or []
    failed = [(i, r) for i, r in enumerate(inst) if r.get("success") is False]
    if inst:
        done = sum(1 for r in inst if r.get("completed") is True)
        out += (f"<p>{len(inst) - len(failed)} of {len(inst)} instances clean"
                + (f", {done} completed" if any("completed" in r for r in inst) else "") + ".</p>")
    if failed:
        shown = failed[:100]
        out += "<h3>Failed instances</h3>" + table(
            ["#", "height [m]", "reflex", "instance", "reason", "peak pitch [rad]", "progress [m]"],
            [[str(i), fmt(r.get("height"), "{:.2f}"), fmt(r.get("reflex")), fmt(r.get("instance")),
              f'<span class="fail">{esc(_reasons(r))}</span>', fmt(r.get("peak_pitch")),
              fmt(r.get("progress"), "{:.2f}")] for i, r in shown], left=0)
        if len(failed) > len(shown):
            out += f"<p>... and {len(failed) - len(shown)} more.</p>"
    return out


def bounding_html(res: dict) -> str:
    """Per-configuration aggregate of a bounding run and, for an ablation, each part's contribution."""
    groups = res.get("groups") or {}
    rows = []
    for name, g in groups.items():
        a = g.get("aggregate") or {}
        rows.append([esc(name), fmt(g.get("kinematic_adjustment")), fmt(g.get("centrifugal")), fmt(a.get("n")),
                     fmt(a.get("falls")), esc(_reason_counts(a.get("failure_reasons"))
                                              if a.get("failure_reasons") is not None
                                              else ", ".join(a.get("fail_reasons") or []) or "-"),
                     f"{fmt(a.get('yaw_error_max_deg_mean'), '{:.2f}')} / "
                     f"{fmt(a.get('yaw_error_max_deg_worst'), '{:.2f}')}",
                     fmt(a.get("yaw_error_rms_deg_mean"), "{:.2f}"),
                     f"{fmt(a.get('speed_error_rms_mean'))} / {fmt(a.get('speed_error_rms_worst'))}",
                     fmt(a.get("yaw_rate_error_rms_mean")), fmt(a.get("periodicity_residual_mean"), "{:.2f}")])
    out = "<h3>Bounding results</h3>" + table(
        ["configuration", "kinematic adj.", "centrifugal", "n", "falls", "failure reasons (runs)",
         "yaw err max [deg] mean / worst", "yaw err rms [deg]", "speed err rms [m/s] mean / worst",
         "yaw-rate err rms [rad/s]", "periodicity"], rows, left=1)
    out += ("<p>Means and worst values over surviving instances; periodicity: median apex-to-apex residual (Eq. C2); "
            "-: not measured (no gait cycle after the settling time of ramp + 1 s, or no surviving instance).</p>")
    contrib = res.get("contributions") or {}
    if contrib:
        crow = []
        for part, d in contrib.items():
            crow.append([esc(part)] + [fmt(d.get(f"{k}_increase_when_off"), "{:+.3f}") for k in
                                       ("yaw_error_max_deg_mean", "yaw_error_rms_deg_mean", "speed_error_rms_mean",
                                        "yaw_rate_error_rms_mean", "falls")])
        out += "<h3>Contribution of each part (increase when switched off)</h3>" + table(
            ["part", "yaw err max [deg]", "yaw err rms [deg]", "speed err rms [m/s]", "yaw-rate err rms", "falls"],
            crow, left=1)
    return out


def ci(interval, spec: str = "{:.3f}") -> str:
    lo, hi = (list(interval or []) + [None, None])[:2]
    return f"[{fmt(lo, spec)}, {fmt(hi, spec)}]"


#: Summary keys of a sweep's outcome levels (:data:`hyqjax.studies.sweep.outcomes.KEYS`): clean keeps the keys of
#: summaries written before the levels, completed has ``completed``-named keys (absent or null in older ones).
SWEEP_LEVELS = (("completed", "completed", "completed_rate", "completed_ci95", "h95_completed_wilson",
                 "h95_completed_logistic"),
                ("clean", "successes", "rate", "ci95", "h95_wilson", "h95_logistic"))


def sweep_html(res: dict) -> str:
    """A sweep's summary, completed and clean: counts, rates and largest safe height per reflex setting, both
    levels vs. height, failure reasons and notes (an older summary without completed shows ``-`` for it)."""
    totals = ", ".join(f"{fmt(res.get(count))} {name}" for name, count, *_ in SWEEP_LEVELS)
    out = (f"<h3>Sweep results</h3><p>{fmt(res.get('n_instances'))} of {fmt(res.get('n_planned'))} planned instances"
           f" ({'complete' if res.get('complete') else 'incomplete'}), {totals}, {fmt(res.get('diverged'))} diverged."
           "</p>")
    by = res.get("by_reflex") or {}
    if by:
        rows = [[esc(name), name_lv, fmt(r.get("n")), fmt(r.get(count)), fmt(r.get(rate), "{:.1%}"), ci(r.get(c95)),
                 fmt(r.get("mean_mobility")), fmt(r.get(hw), "{:.3f}"), fmt(r.get(hl), "{:.3f}")]
                for name, r in by.items() for name_lv, count, rate, c95, hw, hl in SWEEP_LEVELS]
        out += table(["reflex", "outcome", "n", "instances", "rate", "95% CI", "mean mobility", "h95 Wilson [m]",
                      "h95 logistic [m]"], rows, left=2)
        out += ("<p>completed: all four feet on the lower ground, no lost foothold, no joint past its range, no trunk "
                "strike, no tilt, finite; clean: completed and no shin or trunk contact above the strike force. "
                "h95 Wilson: the largest height with the Wilson 95% lower bound >= 0.95 at it and every lower level; "
                "h95 logistic: where a logistic fit vs. height crosses 0.95.</p>")
        for name, r in by.items():
            curve = r.get("height_curve") or []
            if curve:
                out += f"<h4>Completed and clean vs. height, reflex {esc(name)}</h4>" + table(
                    ["height [m]", "n", "completed", "rate", "95% CI", "clean", "rate", "95% CI"],
                    [[fmt(c.get("height"), "{:.3f}"), fmt(c.get("n"))]
                     + [cell for _, count, rate, c95, *_ in SWEEP_LEVELS
                        for cell in (fmt(c.get(count)), fmt(c.get(rate), "{:.1%}"), ci(c.get(c95)))]
                     for c in curve])
    reasons = res.get("failure_reasons") or {}
    if isinstance(reasons, dict) and reasons:
        out += "<h4>Failure reasons (instances not clean)</h4>" + table(
            ["reason", "instances"], [[esc(k), fmt(v)] for k, v in reasons.items()], left=1)
    notes = res.get("notes") or []
    if notes:
        out += "".join(f"<p>Note: {esc(t)}</p>" for t in notes)
    return out


def other_html(res: dict) -> str:
    known = {"provenance", "config", "args", "summary", "instances", "groups", "contributions", "figures",
             "wall_time_s", "env_steps_per_s", "_sweep", "n_instances", "n_planned", "spec_hash", "successes",
             "diverged", "failure_reasons", "by_reflex", "maps", "complete", "rate", "ci95", "completed",
             "completed_rate", "completed_ci95", "notes", "damaged_chunks"}
    rest = sorted(k for k in res if k not in known)
    return f"<p>Other entries of results.json: {', '.join(f'<code>{esc(k)}</code>' for k in rest)}</p>" if rest else ""


def figure(path: str, caption: str) -> str:
    return (f'<figure><img src="{data_uri(path)}" alt="{esc(os.path.basename(path))}">'
            f"<figcaption>{esc(caption)}</figcaption></figure>")


def figures_html(directory: str) -> str:
    pngs = sorted(f for f in os.listdir(directory) if f.lower().endswith(".png"))
    order = {name: i for i, name in enumerate(CAPTIONS)}
    pngs.sort(key=lambda f: (order.get(f, len(order)), f))
    if not pngs:
        return ""
    return "<h3>Figures</h3>" + "".join(figure(os.path.join(directory, f), CAPTIONS.get(f, f)) for f in pngs)


def renders_html(directory: str, max_embed_bytes: int) -> str:
    """Stills (PNG) and videos (GIF / MP4) under ``directory/render``: stills embedded, videos embedded when small."""
    rdir = os.path.join(directory, RENDER_DIR)
    if not os.path.isdir(rdir):
        return ""
    files = sorted(os.listdir(rdir))
    stills = [f for f in files if f.lower().endswith(".png")]
    videos = [f for f in files if f.lower().endswith((".gif", ".mp4"))]
    if not stills and not videos:
        return ""
    out = "<h3>Renders</h3>"
    if stills:
        out += '<div class="stills">' + "".join(figure(os.path.join(rdir, f), f) for f in stills) + "</div>"
    for f in videos:
        p = os.path.join(rdir, f)
        size = os.path.getsize(p)
        rel = os.path.join(RENDER_DIR, f)
        if size <= max_embed_bytes and f.lower().endswith(".gif"):
            out += figure(p, f)
        elif size <= max_embed_bytes:
            out += (f'<figure><video controls loop muted src="{data_uri(p)}"></video>'
                    f"<figcaption>{esc(f)}</figcaption></figure>")
        else:
            out += f'<p>Video (not embedded, {size / 1e6:.1f} MB): <a href="{esc(rel)}">{esc(rel)}</a></p>'
    return out


def check_html(lines: list[str], ok: bool) -> str:
    """The result of checking an experiment's stored data (e.g. a sweep store's chunks), first in its section."""
    cls = "ok" if ok else "fail"
    return (f"<div class='{cls}'><p><strong>{'Store verified' if ok else 'Store damaged'}:</strong> {esc(lines[0])}</p>"
            + "".join(f"<p>{esc(t.strip())}</p>" for t in lines[1:]) + "</div>")


def section(directory: str, root: str, max_embed_bytes: int, check: tuple[bool, list[str]] | None = None) -> str:
    res = load_results(directory)
    rel = os.path.relpath(directory, root)
    title = os.path.basename(os.path.abspath(directory)) if rel == "." else rel
    kind = ("sweep" if res.get("_sweep") else "step-down" if "summary" in res and "instances" in res
            else "bounding" if "groups" in res else "experiment")
    out = f"<h2>{esc(title)} <small>({kind})</small></h2>"
    if check is not None:
        out += check_html(check[1], check[0])
    out += provenance_html(res) + options_html(res)
    if kind == "step-down":
        out += stepdown_html(res)
    elif kind == "bounding":
        out += bounding_html(res)
    elif kind == "sweep":
        out += sweep_html(res)
    out += other_html(res) + figures_html(directory) + renders_html(directory, max_embed_bytes)
    return out


def build_report(root: str, out_path: str | None = None, title: str | None = None,
                 max_embed_mb: float = 8.0, checks: dict[str, tuple[bool, list[str]]] | None = None
                 ) -> tuple[str, list[str]]:
    """Write the HTML report of ``root`` (default ``root/report.html``); returns ``(path, experiment dirs)``.

    ``checks``: per experiment directory, ``(ok, lines)`` of a check of its stored data (``hyqjax report`` verifies
    every sweep store, :func:`hyqjax.studies.sweep.verify_store`), shown first in its section.
    Raises ``FileNotFoundError`` when ``root`` holds no results.json at any depth.
    """
    if not os.path.isdir(root):
        raise FileNotFoundError(f"{root} is not a directory")
    dirs = find_result_dirs(root)
    if not dirs:
        raise FileNotFoundError(f"no {RESULTS_FILE} or {SWEEP_FILE} in {root} or its subdirectories "
                                f"(run an experiment with --out {root})")
    out_path = out_path or os.path.join(root, "report.html")
    title = title or f"hyqjax results: {os.path.basename(os.path.abspath(root))}"
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(title)}</title>",
             f"<style>{STYLE}</style></head><body><h1>{esc(title)}</h1>",
             f"<p>Built {esc(stamp)} from <code>{esc(os.path.abspath(root))}</code>: {len(dirs)} experiment(s).</p>"]
    for d in dirs:
        try:
            parts.append(section(d, os.path.abspath(root), int(max_embed_mb * 1e6), (checks or {}).get(d)))
        except (OSError, ValueError) as err:
            parts.append(f"<h2>{esc(os.path.relpath(d, root))}</h2><p class='fail'>could not read: {esc(err)}</p>")
    parts.append("</body></html>")
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    tmp = out_path + ".tmp"
    with open(tmp, "w") as f:
        f.write("\n".join(parts))
    os.replace(tmp, out_path)
    return out_path, dirs
