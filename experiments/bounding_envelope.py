"""The bound's command envelope: fall rate and worst yaw error per command over randomised friction and payload.

    python -m experiments.bounding_envelope --out docs/results --name bounding_envelope_default
    python -m experiments.bounding_envelope --params out/robust/params_gradient.json --name bounding_envelope_gradient
    python -m experiments.bounding_envelope --preset bound_robust --name bounding_envelope_robust

Sweeps forward speed x yaw rate x lateral speed (``--speeds LO HI STEP`` and so on), ``--instances`` per
command with friction in ``--friction`` and payload in ``--payload`` (the same draws for every command), runs
``--duration`` s each as one batch (``--impl warp`` on a GPU), and writes ``OUT/NAME.json`` (per command: failures
and reasons, fall rate with its Wilson interval, worst / 95th-percentile yaw error, rate above 4 deg; the area
of the map with a fall rate below 1%; provenance) and ``OUT/NAME.png``. ``--params FILE`` runs the controller
with stored optimised parameters (:func:`hyqjax.bounding.robust.save_params`), ``--preset NAME`` with a bounding
preset of :mod:`hyqjax.presets` (default ``bound_paper``, the paper's gains). Bad options: one line naming the
option, exit code 2, before anything compiles.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from hyqjax.cli.common import add_devices_argument, apply_devices


#: The gains a map runs without --preset or --params: the paper's (the maps of docs/bounding.md named "default").
DEFAULT_PRESET = "bound_paper"


def grid(name, lo, hi, step, lim):
    from hyqjax.bounding.batch import SettingError

    if not (np.isfinite([lo, hi, step]).all() and step > 0 and -lim <= lo <= hi <= lim):
        raise SettingError(name, f"--{name.replace('_', '-')} must be LO HI STEP with -{lim:g} <= LO <= HI <= "
                                 f"{lim:g} and STEP > 0, got {lo:g} {hi:g} {step:g}")
    n = int(np.floor((hi - lo) / step + 1e-6)) + 1
    if n > 200:
        raise SettingError(name, f"--{name.replace('_', '-')} gives {n} values; at most 200")
    return tuple(np.round(lo + step * np.arange(n), 6))


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--speeds", type=float, nargs=3, default=(-1.0, 1.2, 0.2), metavar=("LO", "HI", "STEP"),
                    help="forward speed commands (m/s), in [-1.5, 1.5]")
    ap.add_argument("--yaw-rates", type=float, nargs=3, default=(-1.0, 1.0, 0.25), metavar=("LO", "HI", "STEP"),
                    help="yaw-rate commands (rad/s), in [-1.5, 1.5]")
    ap.add_argument("--lateral-speeds", type=float, nargs="+", default=(0.0,), metavar="V",
                    help="lateral speed commands (m/s), in [-0.5, 0.5]")
    ap.add_argument("--instances", type=int, default=32, help="instances per command")
    ap.add_argument("--friction", type=float, nargs=2, default=(0.4, 1.0), metavar=("LO", "HI"))
    ap.add_argument("--payload", type=float, nargs=2, default=(0.0, 15.0), metavar=("LO", "HI"), help="kg")
    ap.add_argument("--duration", type=float, default=8.0, help="simulated time per instance (s), a multiple of 0.4")
    ap.add_argument("--ramp-time", type=float, default=1.0, help="command ramp (s)")
    ap.add_argument("--max-batch", type=int, default=16384, help="instances per compiled batch")


def spec_of(args):
    from hyqjax.bounding import envelope

    return envelope.EnvelopeSpec(speeds=grid("speeds", *args.speeds, 1.5), yaw_rates=grid("yaw_rates", *args.yaw_rates,
                                                                                          1.5),
                                 lateral_speeds=tuple(args.lateral_speeds), instances=args.instances,
                                 friction=tuple(args.friction), payload=tuple(args.payload), duration=args.duration,
                                 ramp_time=args.ramp_time, seed=args.seed)


def check_duration(d):
    from hyqjax.bounding.batch import SettingError

    if abs(d / 0.4 - round(d / 0.4)) > 1e-6:
        raise SettingError("duration", f"--duration must be a multiple of the gait period 0.4 s, got {d:g}")


def run_map(spec, base, impl, max_batch, name, out, log=print, command: str | None = None) -> dict:
    """Simulate one map, write ``out/name.json`` and ``out/name.png``; returns the JSON dict."""
    from hyqjax.bounding import envelope
    from hyqjax.io import atomic

    t0 = time.time()
    cols = envelope.run(spec, base, impl, max_batch,
                        progress=lambda d, n: log(f"{name}: {d}/{n} instances ({time.time() - t0:.0f} s)"))
    wall = time.time() - t0
    pc = envelope.summarise(spec, cols)
    area = envelope.safe_area(spec, pc)
    prov = atomic.provenance(seed=spec.seed)
    prov["command"] = command or " ".join(["python -m experiments.bounding_envelope", *sys.argv[1:]])
    res = dict(provenance=prov, spec=spec.to_dict(), wall_time_s=wall, impl=impl, instances=spec.size,
               overall=envelope.group_summary(cols), safe_area=area, per_command=pc)
    fig = envelope.figure(spec, {name: pc}, os.path.join(out, f"{name}.png"))
    res["figures"] = [fig]
    atomic.write_json(os.path.join(out, f"{name}.json"), res)
    log(f"{name}: {spec.size} instances in {wall:.0f} s; failures {res['overall']['failures']}; area with fall rate "
        f"< 1%: {area['area_point']:.3f} of {area['total_area']:.3f} (m/s x rad/s)")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.bounding_envelope", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(ap)
    ap.add_argument("--preset", default=None, metavar="NAME",
                    help="a bounding preset of hyqjax.presets (`hyqjax presets --kind bound`); default: bound_paper, "
                         "the paper's gains, whose maps docs/bounding.md shows as 'default'")
    ap.add_argument("--params", metavar="FILE",
                    help="optimised parameters (a file of hyqjax.bounding.robust.save_params; the old names robust "
                         "and robust_8s are the presets bound_robust_grad and bound_robust)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--impl", default="auto", help="MJX implementation: auto | jax | warp")
    ap.add_argument("--out", default="docs/results")
    ap.add_argument("--name", default="bounding_envelope", help="output file stem (letters, digits, . _ -)")
    add_devices_argument(ap)
    args = ap.parse_args(argv)
    try:
        from hyqjax.bounding import robust
        from hyqjax.sim import backend

        backend.validate_impl(args.impl)
        check_duration(args.duration)
        spec = spec_of(args)
        if not all(c.isalnum() or c in "._-" for c in args.name) or not args.name:
            raise ValueError(f"--name may hold letters, digits, '.', '_' and '-' only, got {args.name!r}")
        if not (1 <= args.max_batch <= 1 << 20):
            raise ValueError(f"--max-batch must be in [1, 1048576], got {args.max_batch}")
        if args.params and args.preset:
            raise ValueError("give one of --params and --preset")
        if args.params:
            base = robust.params_from_values(robust.load_params(args.params))
        else:
            from hyqjax import presets

            base = presets.load(presets.check_kind(args.preset or DEFAULT_PRESET, "bound").name)
        impl = backend.resolve_impl(args.impl)
        apply_devices(args)
    except ValueError as e:
        name = getattr(e, "name", None)
        print(f"error: --{name.replace('_', '-')}: {e}" if name else f"error: {e}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    run_map(spec, base, impl, args.max_batch, args.name, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
