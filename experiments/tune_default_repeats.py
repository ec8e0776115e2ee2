"""``hyqjax tune`` with its defaults, run once per training seed, and what the runs return judged on held-out
step-downs against the default tuner's targets (:mod:`hyqjax.studies.tune.study.targets`).

    python -m experiments.tune_default_repeats --out DIR --impl warp                        # one GPU
    python -m experiments.tune_default_repeats --out DIR --impl c --seeds 0 1 --wall-minutes 1 \\
        --heldout 4 --instances 2 --tune-option=--quick                                    # CPU check

1. ``runs``: ``hyqjax tune --out DIR/run_S --seed S --impl IMPL --wall-minutes W`` for every ``--seeds`` S, one after
   the other, every other option at the tuner's default (``--heldout`` and ``--tune-option`` pass further options;
   the tuner's own held-out evaluation is not what is judged). A finished run is kept; a killed one goes on from
   its stored state (the tuner resumes); ``--max-minutes`` stops before a run that would not finish in the time
   left (exit status 75: the same command goes on). ``--segment-minutes M`` runs budgets longer than one sitting
   (10 or 30 minutes inside calls or jobs of a few minutes): each run stops on purpose after M minutes (or the
   time left of ``--max-minutes``) with its state stored (the tuner's ``--segment-minutes``), and the next call
   goes on from there. ``--gpus K`` runs K at a time, each on a GPU of its own (``CUDA_VISIBLE_DEVICES``), so
   that every run still has one whole GPU for its wall-clock budget (on a fresh machine each builds MuJoCo Warp's
   kernels, which its clock leaves out of its budget); the held-out map then runs on every device.
   ``--runs-only`` stops here (exit 0 once every run is finished): runs made in several directories (or on several
   machines) are then judged together from one directory holding them all.
2. ``heldout``: the returned sets (variants ``run_S``), the ``--references`` presets and any ``--extra-run`` on the
   same held-out instances (``python -m experiments.reach_map`` with :data:`targets.HELDOUT`: the wide spread, a
   seed and heights the tuner never saw), in ``DIR/heldout``. A run that recorded checkpoints before the end of
   its budget (the tuner's default ``--wall-minutes 3 10 30``; a driver given ``--wall-minutes`` passes that one
   budget alone) also puts the iterate it held at each of them on the map, as ``run_S@3min`` and ``run_S@10min``.
3. ``targets``: per set, clean success pooled up to 26 cm, the worst clean rate at a height up to 24 cm, h90 and
   clean success at the farthest starts (10-15 cm), and the iterate each run returned; over the runs, the mean
   with its 95% t-interval, the range, and the four targets (``DIR/targets.json``, ``DIR/targets.md``); with
   checkpoints, the same mean, interval and range per budget (3, 10, 30 minutes). ``--judge-only`` runs nothing
   and judges what ``DIR`` holds again.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from experiments.gpu_slots import gpu_slots

PROG = "python -m experiments.tune_default_repeats"
#: Minutes a default run takes beyond its budget: the final re-evaluation, the held-out runs of the tuner, start-up.
OVERHEAD_MINUTES = 1.5
#: the shortest segment worth starting: imports, the kernel load and compiles, then some of the search
MIN_SEGMENT_MINUTES = 2.0
#: exit status of a run (and of the driver) stopped on purpose with its state stored
PAUSED = 75


def parse(argv):
    from hyqjax.studies.tune.study import targets

    from hyqjax.cli.app import Parser

    ap = Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/tune_default_repeats")
    ap.add_argument("--impl", default="auto", help="simulator: auto | jax | warp | c")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="training seeds, one run each")
    ap.add_argument("--wall-minutes", type=float, default=None,
                    help="each run's budget (default: the tuner's, 30 minutes)")
    ap.add_argument("--heldout", type=int, default=None, help="the tuner's own held-out instances (its --heldout)")
    ap.add_argument("--tune-option", action="append", default=[], metavar="OPTION",
                    help="a further option of hyqjax tune, e.g. --tune-option=--quick (repeatable)")
    ap.add_argument("--references", nargs="*", default=["clean", "reach"],
                    help="crawl presets evaluated beside the runs (default: the tuner's default start, clean, and "
                         "reach)")
    ap.add_argument("--extra-run", action="append", default=[], metavar="NAME:PATH:METHOD[:field=value,...]",
                    help="a further set from a tuning results.json (the reach map's --tuned-run)")
    ap.add_argument("--instances", type=int, default=targets.HELDOUT["instances"], help="held-out runs per height")
    ap.add_argument("--map-seed", type=int, default=None,
                    help=f"the held-out map's draw seed (default {targets.HELDOUT['seed']}); a new one gives instances "
                         "that no earlier study or preset choice saw")
    ap.add_argument("--runs-only", action="store_true",
                    help="run the tuner runs and stop (exit 0 once all are finished): no held-out map, no judgement")
    ap.add_argument("--judge-only", action="store_true",
                    help="run nothing: judge the stored runs and DIR/heldout/reach_map.json again")
    ap.add_argument("--heldout-dir", default=None, metavar="MAP_DIR",
                    help="with --judge-only: judge the runs on this finished reach map instead of DIR/heldout (one "
                         "made elsewhere, e.g. in C MuJoCo, or merged from parts by python -m "
                         "experiments.reach_map_merge); targets.json and targets.md go beside it")
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="stop (exit 75) before a run that would not finish in this many minutes of this process")
    ap.add_argument("--segment-minutes", type=float, default=None,
                    help="stop each run after this many minutes of it (at most the time left of --max-minutes), its "
                         "state stored, exit status 75 once the running ones stop: budgets longer than one call")
    ap.add_argument("--gpus", type=int, default=1,
                    help="runs at once, each on a GPU of its own (CUDA_VISIBLE_DEVICES; each run's clock leaves "
                         "MuJoCo Warp's kernel build out of its budget); the held-out map then runs on every device. "
                         "Default 1: one run after another on the default device")
    args = ap.parse_args(argv)
    if not args.seeds or len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        raise ValueError(f"--seeds {args.seeds}: distinct non-negative integers, at least one")
    if args.wall_minutes is not None and not 0 < args.wall_minutes <= 600:
        raise ValueError(f"--wall-minutes {args.wall_minutes}: must be in (0, 600]")
    if args.heldout is not None and not 1 <= args.heldout <= 10**6:
        raise ValueError(f"--heldout {args.heldout}: must be in [1, 1000000]")
    if not 1 <= args.instances <= 100000:
        raise ValueError(f"--instances {args.instances}: must be in [1, 100000]")
    if args.max_minutes is not None and args.max_minutes <= 0:
        raise ValueError(f"--max-minutes {args.max_minutes}: must be > 0")
    if args.runs_only and args.judge_only:
        raise ValueError("--runs-only and --judge-only: give one (the first runs, the second judges)")
    if args.heldout_dir is not None and not args.judge_only:
        raise ValueError(f"--heldout-dir {args.heldout_dir}: only with --judge-only (a map made elsewhere is judged, "
                         "not made)")
    if args.heldout_dir is not None and not os.path.isfile(os.path.join(args.heldout_dir, "reach_map.json")):
        raise ValueError(f"--heldout-dir {args.heldout_dir}: no reach_map.json there (give a finished reach map's "
                         "--out)")
    if args.segment_minutes is not None and not MIN_SEGMENT_MINUTES <= args.segment_minutes <= 600:
        raise ValueError(f"--segment-minutes {args.segment_minutes}: must be in [{MIN_SEGMENT_MINUTES:g}, 600]")
    if args.map_seed is not None and not 0 <= args.map_seed < 2**31:
        raise ValueError(f"--map-seed {args.map_seed}: must be in [0, 2147483647]")
    if not 1 <= args.gpus <= 64:
        raise ValueError(f"--gpus {args.gpus}: must be in [1, 64]")
    from hyqjax import presets

    for r in args.references:
        try:
            presets.check_kind(r, "crawl", "--references")
        except ValueError as e:
            raise ValueError(str(e)) from None
    return args


def tune_argv(args, seed: int, segment: float | None = None) -> list[str]:
    """The ``hyqjax tune`` command of run ``seed``; ``segment``: its ``--segment-minutes``."""
    argv = [sys.executable, "-m", "hyqjax.cli", "tune", "--out", run_dir(args, seed), "--seed", str(seed),
            "--impl", args.impl]
    if args.wall_minutes is not None:
        argv += ["--wall-minutes", f"{args.wall_minutes:g}"]
    if args.heldout is not None:
        argv += ["--heldout", str(args.heldout)]
    if segment is not None:
        argv += ["--segment-minutes", f"{segment:.2f}"]
    return argv + list(args.tune_option)


def run_dir(args, seed: int) -> str:
    return os.path.join(args.out, f"run_{seed}")


def complete(path: str) -> bool:
    try:
        with open(os.path.join(path, "results.json")) as f:
            return bool(json.load(f).get("complete"))
    except (OSError, ValueError):
        return False


def main(argv=None) -> int:
    try:
        args = parse(argv)
    except ValueError as e:
        print(f"tune_default_repeats: {e}", file=sys.stderr)
        return 2
    from hyqjax.io import atomic
    from hyqjax.studies.tune import names
    from hyqjax.studies.tune.study import targets

    t0 = time.time()
    os.makedirs(args.out, exist_ok=True)
    budget = args.wall_minutes if args.wall_minutes is not None else names.DEFAULT_WALL_MINUTES[-1]
    rc = 0 if args.judge_only else _run_all(args, t0, budget)
    if rc:
        return rc
    if args.runs_only:
        print(f"tune_default_repeats: every run is finished under {args.out} (--runs-only: no held-out map); wall "
              f"{time.time() - t0:.1f} s in all (this process: the runs it launched)")
        return 0
    from experiments import reach_map

    runs = {f"run_{s}": os.path.join(run_dir(args, s), "results.json") for s in args.seeds}
    recorded = {name: run_checkpoints(path) for name, path in runs.items()}
    checkpoints = {name: minutes[:-1] for name, minutes in recorded.items()}  # the end: the returned set, run_S
    budgets = None
    if any(checkpoints.values()):
        budgets = {}
        for name, minutes in recorded.items():
            for m in minutes:
                budgets.setdefault(m, []).append(name if m == minutes[-1] else targets.checkpoint_variant(name, m))
    heldout = args.heldout_dir or os.path.join(args.out, "heldout")
    judged = args.heldout_dir or args.out  # where targets.json and targets.md go
    rm_argv = targets.reach_map_arguments(runs, args.references, args.extra_run, args.impl, heldout, args.instances,
                                          args.map_seed, checkpoints=checkpoints)
    if args.gpus > 1:
        rm_argv += ["--devices", "all"]
    if not args.judge_only:
        print(f"[{time.strftime('%H:%M:%S')}] held-out: python -m experiments.reach_map {' '.join(rm_argv)}",
              flush=True)
        rc = reach_map.main(rm_argv)
        if rc != 0:
            return rc
    try:
        with open(os.path.join(heldout, "reach_map.json")) as f:
            heldout_map = json.load(f)
        cells = heldout_map["cells"]
        stored = [_read(os.path.dirname(p)) for p in runs.values()]
    except (OSError, ValueError, KeyError) as e:
        print(f"tune_default_repeats: cannot read the held-out map or a run under {args.out} ({e})", file=sys.stderr)
        return 2
    references = list(args.references) + [t.split(":", 1)[0] for t in args.extra_run]
    starts = {(r.get("config") or {}).get("start_preset") for r in stored}  # the preset every run started from
    start = starts.pop() if len(starts) == 1 else None
    try:
        summary = targets.judge(cells, list(runs), references,
                                seed=(heldout_map.get("provenance") or {}).get("seed", args.map_seed),
                                budgets=budgets, start=start if start in references else None)
    except ValueError as e:
        print(f"tune_default_repeats: {heldout}/reach_map.json: {e}", file=sys.stderr)
        return 2
    command = "python -m experiments.reach_map " + " ".join(rm_argv)
    if args.heldout_dir:  # a map made elsewhere: the command it recorded
        command = (heldout_map.get("provenance") or {}).get("command") or command
    elif args.judge_only:  # the command that made the stored map, where an earlier judgement recorded it
        try:
            command = _read_targets(judged).get("reach_map_command") or command
        except (OSError, ValueError):
            pass
    ends = {minutes[-1] for minutes in recorded.values() if minutes}
    summary.update(budget_minutes=ends.pop() if len(ends) == 1 else budget, seeds=args.seeds, reach_map_command=command,
                   heldout_device=heldout_map.get("device"), heldout_wall_s=heldout_map.get("wall_s"),
                   run_walls_s={k: r.get("wall_s") for k, r in zip(runs, stored)},
                   returned={k: _returned(r) for k, r in zip(runs, stored)})
    atomic.write_json(os.path.join(judged, "targets.json"), summary)
    text = targets.table(summary)
    atomic.atomic_write(os.path.join(judged, "targets.md"), lambda f: f.write((text + "\n").encode()))
    print(text)
    walls = [w for w in summary["run_walls_s"].values() if w]
    print(f"wall {time.time() - t0:.1f} s in all (this process: the runs it launched, the held-out map, the "
          f"judgement); the runs' own walls {sum(walls):.0f} s over {len(walls)} runs; wrote {judged}/targets.md")
    return 0


def _launch(args, seed: int, env: dict | None = None, segment: float | None = None):
    d = run_dir(args, seed)
    os.makedirs(d, exist_ok=True)
    cmd = tune_argv(args, seed, segment)
    where = f" on GPU {env['CUDA_VISIBLE_DEVICES']}" if env else ""
    print(f"[{time.strftime('%H:%M:%S')}] run {seed}{where}: {' '.join(cmd[1:])}", flush=True)
    return cmd, d


def _run_all(args, t0: float, budget: float) -> int:
    """Every run not complete yet: one after another (``--gpus 1``), or ``--gpus`` at a time, each on a GPU of its
    own. A run is launched only when it can finish within
    ``--max-minutes`` (else exit status 75 once the running ones end); with ``--segment-minutes`` a run is launched
    when a segment of at least :data:`MIN_SEGMENT_MINUTES` fits, and one that stops with its state stored (exit
    status 75) is left for the next call. A failed run ends the driver with its status."""
    def left():
        return None if args.max_minutes is None else args.max_minutes - (time.time() - t0) / 60

    def stop(todo_note=""):
        todo = sum(not complete(run_dir(args, s)) for s in args.seeds)
        lm = left()
        print(f"tune_default_repeats: stopping with {todo} run(s) to go"
              + ("" if lm is None else f" ({lm:.1f} min left of --max-minutes)")
              + f"{todo_note}; the same command goes on", flush=True)
        return PAUSED

    def segment():
        """The next run's ``--segment-minutes`` (None: the run goes to the end of its budget)."""
        if args.segment_minutes is None:
            return None
        lm = left()
        return args.segment_minutes if lm is None else min(args.segment_minutes, lm - 0.5)

    def fits():
        lm = left()
        if args.segment_minutes is not None:
            return lm is None or lm - 0.5 >= MIN_SEGMENT_MINUTES
        return lm is None or lm >= budget + OVERHEAD_MINUTES

    def failed(seed, rc):
        print(f"tune_default_repeats: run {seed} ended with exit status {rc} (log: {run_dir(args, seed)}/run.log)",
              file=sys.stderr)
        return rc or 1

    paused = []

    def ended(seed, rc):
        """0 when run ``seed`` finished or stopped on purpose (its state stored), else the failure's status."""
        if rc == PAUSED and args.segment_minutes is not None:
            paused.append(seed)
            print(f"[{time.strftime('%H:%M:%S')}] run {seed} stopped after its segment, its state stored", flush=True)
            return 0
        return failed(seed, rc) if rc != 0 or not complete(run_dir(args, seed)) else 0

    todo = [s for s in args.seeds if not complete(run_dir(args, s))]
    serial = todo if args.gpus == 1 else []
    for seed in serial:
        if not fits():
            return stop()
        cmd, d = _launch(args, seed, segment=segment())
        with open(os.path.join(d, "run.log"), "a") as log:
            rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
        status = ended(seed, rc)
        if status:
            return status
        if paused and args.gpus == 1:
            return stop()
    queue = [s for s in todo if s not in serial or s in paused]
    running: dict = {}  # slot -> (seed, process, log file)
    slots = gpu_slots(args.gpus)
    status = 0
    while queue or running:
        for slot in slots:
            if slot in running or not queue or status:
                continue
            if not fits():
                break
            seed = queue.pop(0)
            env = dict(os.environ, CUDA_VISIBLE_DEVICES=slot)
            cmd, d = _launch(args, seed, env, segment())
            log = open(os.path.join(d, "run.log"), "a")
            running[slot] = (seed, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log)
        if not running:
            return status or (stop() if queue or paused else 0)
        time.sleep(1.0)
        for slot, (seed, proc, log) in list(running.items()):
            rc = proc.poll()
            if rc is None:
                continue
            log.close()
            del running[slot]
            if seed in paused:  # the first run's next segment, on a GPU of its own, ended
                paused.remove(seed)
            failure = ended(seed, rc)
            if failure and not status:
                status = failure
    return status or (stop() if paused else 0)


def run_checkpoints(path: str) -> list[float]:
    """The checkpoints (minutes, the last the end of its budget) at which the run at ``path`` (its
    ``results.json``) recorded the iterate it held; none for a run that cannot be read (the judgement names it)."""
    from hyqjax.studies.tune import tuned

    try:
        res = tuned.read(path)
        return tuned.checkpoint_minutes(res, tuned.pick_run(res, None, path))
    except ValueError:
        return []


def _read_targets(d: str) -> dict:
    with open(os.path.join(d, "targets.json")) as f:
        res = json.load(f)
    cmd = res.get("reach_map_command")
    if isinstance(cmd, list):  # stored as an argument list
        res["reach_map_command"] = " ".join(cmd)
    return res


def _read(d: str) -> dict:
    with open(os.path.join(d, "results.json")) as f:
        return json.load(f)


def _returned(res: dict) -> dict | None:
    """The returned iterate of a run's one search: its final re-evaluation's choice (iteration, validation and
    pooled clean rates) or, where the selection validated a single iterate and so re-evaluated nothing, that one
    (pooled clean None)."""
    run = next(iter((res.get("runs") or {}).values()), None)
    fr = (run or {}).get("final_reevaluation") or {}
    if fr.get("candidates"):
        c = fr["candidates"][fr["chosen"]]
        return dict(iteration=c["iteration"], validation_clean=c["validation_clean"], pooled_clean=c["pooled_clean"])
    chosen = [x for x in ((run or {}).get("selection") or {}).get("log", []) if x.get("selected")]
    if not chosen:
        return None
    return dict(iteration=chosen[-1]["iteration"], validation_clean=chosen[-1]["clean"], pooled_clean=None)


if __name__ == "__main__":
    raise SystemExit(main())
