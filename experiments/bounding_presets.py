"""The bounding presets side by side on the same instances: the paper's gains against the default (robust) ones.

    python -m experiments.bounding_presets --impl warp --instances 1024 --out out/bounding_presets   # one GPU
    python -m experiments.bounding_presets --impl c --instances 2 --duration 2.4 --out /tmp/bp          # CPU check

Every preset of ``--presets`` (default ``bound_paper bound_robust``, :mod:`hyqjax.presets`) runs the same
``--instances`` randomised instances (initial apex perturbation, friction, payload and its position drawn from
``--seed``, the same draws for every preset and command) of ``--duration`` s in three conditions:

* ``nominal``: the nominal command (0.5 m/s, 0.3 rad/s) with ``hyqjax bound``'s randomisation (friction 0.7-1.0,
  payload 0-5 kg);
* ``nominal, low friction, 10 kg``: the same command at friction ``--friction`` (0.5-0.6) with a ``--payload``
  (10 kg) payload;
* ``corners``: the corners of the trained command box, forward speed ``--corner-speeds`` (0 and 1.0 m/s) x yaw
  rate ``--corner-yaw-rates`` (-0.8 and +0.8 rad/s), at that friction and payload.

Per preset, condition and command: runs that fall (with the Wilson 95 % interval of the rate) and how, the worst
and 95th-percentile yaw error over the runs that stand, the mean absolute forward-speed error after the ramp.
Writes ``OUT/bounding_presets.json`` (with provenance: the command, device, versions, seed) and
``OUT/bounding_presets.md`` (the table), and prints the table. Every batch has ``--instances`` rows, so one
compiled program serves every preset and command. Bad options: one line, exit code 2, before anything compiles.
"""
from __future__ import annotations

import argparse
import os
import sys
import time


NOMINAL = (0.5, 0.3)


def conditions(args) -> list[tuple[str, tuple, tuple, tuple, tuple]]:
    """``(name, speeds, yaw rates, friction, payload)`` of every condition."""
    fr, pl = tuple(args.friction), (float(args.payload), float(args.payload))
    return [("nominal", (NOMINAL[0],), (NOMINAL[1],), (0.7, 1.0), (0.0, 5.0)),
            ("nominal, low friction, payload", (NOMINAL[0],), (NOMINAL[1],), fr, pl),
            ("corners, low friction, payload", tuple(args.corner_speeds), tuple(args.corner_yaw_rates), fr, pl)]


def specs(args):
    from hyqjax.bounding import envelope

    return [(name, envelope.EnvelopeSpec(speeds=sp, yaw_rates=yr, lateral_speeds=(0.0,), instances=args.instances,
                                         friction=fr, payload=pl, duration=args.duration, seed=args.seed))
            for name, sp, yr, fr, pl in conditions(args)]


def table(rows: list[dict]) -> str:
    head = ("| preset | condition | command (m/s, rad/s) | falls [95 %] | fall reasons | worst yaw (deg) | "
            "yaw p95 (deg) | mean abs speed error (m/s) |\n|---|---|---|---:|---|---:|---:|---:|")
    out = [head]
    for r in rows:
        ci = r["fall_rate_ci95"]
        yw = "-" if r["yaw_error_worst_deg"] is None else f"{r['yaw_error_worst_deg']:.2f}"
        p95 = "-" if r["yaw_error_p95_deg"] is None else f"{r['yaw_error_p95_deg']:.2f}"
        se = r.get("speed_error_mean_abs")
        reasons = ", ".join(f"{k.replace('fell_', '')} {v}" for k, v in r["reasons"].items()) or "-"
        out.append(f"| `{r['preset']}` | {r['condition']} | ({r['speed']:g}, {r['yaw_rate']:g}) | {r['failures']} of "
                   f"{r['n']} [{100 * ci[0]:.2f}-{100 * ci[1]:.2f} %] | {reasons} | {yw} | {p95} | "
                   f"{'-' if se is None else f'{se:.3f}'} |")
    return "\n".join(out)


def add_condition_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of the six conditions (:func:`specs`): runs per condition and command, their duration, the
    low-friction conditions' friction and payload, the corners' speeds and yaw rates (also
    ``experiments.bounding_refine``'s held-out conditions)."""
    ap.add_argument("--instances", type=int, default=1024, help="runs per parameter set, condition and command")
    ap.add_argument("--duration", type=float, default=8.0, help="simulated seconds per run, a multiple of 0.4")
    ap.add_argument("--friction", type=float, nargs=2, default=(0.5, 0.6), metavar=("LO", "HI"),
                    help="friction of the low-friction conditions")
    ap.add_argument("--payload", type=float, default=10.0, metavar="KG", help="payload of the low-friction conditions")
    ap.add_argument("--corner-speeds", type=float, nargs="+", default=(0.0, 1.0), metavar="V")
    ap.add_argument("--corner-yaw-rates", type=float, nargs="+", default=(-0.8, 0.8), metavar="W")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.bounding_presets", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["bound_paper", "bound_robust"], metavar="NAME",
                    help="bounding presets (`hyqjax presets --kind bound`)")
    add_condition_arguments(ap)
    ap.add_argument("--seed", type=int, default=2911)
    ap.add_argument("--impl", default="auto", help="simulator: auto | jax | warp | c")
    ap.add_argument("--out", default="out/bounding_presets")
    args = ap.parse_args(argv)
    try:
        from hyqjax import presets
        from hyqjax.bounding import batch as bbatch
        from hyqjax.sim import backend
        from hyqjax.studies import tasks

        impls = tasks.get("bound").impls
        backend.validate_impl(args.impl, impls)
        for n in args.presets:
            presets.check_kind(n, "bound", "--presets")
        if len(set(args.presets)) != len(args.presets):
            raise ValueError("--presets names a preset twice")
        if abs(args.duration / 0.4 - round(args.duration / 0.4)) > 1e-6:
            raise ValueError(f"--duration must be a multiple of the gait period 0.4 s, got {args.duration:g}")
        if not 0.0 <= args.payload <= 100.0:
            raise ValueError(f"--payload must be in [0, 100] kg, got {args.payload:g}")
        sp = specs(args)
        bases = {n: presets.load(n) for n in args.presets}
        impl = backend.resolve_impl(args.impl, impls)
    except (ValueError, bbatch.SettingError) as e:
        print(f"bounding_presets: {e}", file=sys.stderr)
        return 2
    from hyqjax.bounding import envelope
    from hyqjax.io import atomic

    os.makedirs(args.out, exist_ok=True)
    rows, t0 = [], time.time()
    for name in args.presets:
        for cond, spec in sp:
            t1 = time.time()
            cols = envelope.run(spec, bases[name], impl, max_batch=args.instances)
            for c in envelope.summarise(spec, cols):
                rows.append(dict(preset=name, condition=cond, friction=list(spec.friction),
                                 payload=list(spec.payload), **c))
            print(f"{name}, {cond}: {spec.size} runs in {time.time() - t1:.0f} s", flush=True)
    prov = atomic.provenance(seed=args.seed)
    prov["command"] = " ".join(["python -m experiments.bounding_presets", *sys.argv[1:]] if argv is None else
                               ["python -m experiments.bounding_presets", *argv])
    md = table(rows)
    res = dict(provenance=prov, impl=impl, instances=args.instances, duration=args.duration, seed=args.seed,
               presets=args.presets, conditions=[dict(name=n, speeds=list(s.speeds), yaw_rates=list(s.yaw_rates),
                                                      friction=list(s.friction), payload=list(s.payload))
                                                 for n, s in sp],
               wall_time_s=time.time() - t0, rows=rows)
    atomic.write_json(os.path.join(args.out, "bounding_presets.json"), res)
    with open(os.path.join(args.out, "bounding_presets.md"), "w") as f:
        f.write(f"{md}\n\n`{prov['command']}`; {', '.join(prov.get('devices', []) or [])} {prov.get('date', '')}\n")
    print(md)
    print(f"wrote {args.out}/bounding_presets.json and bounding_presets.md ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
