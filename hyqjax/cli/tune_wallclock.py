"""The run of ``hyqjax tune`` and of the equal-wall-clock study (``python -m experiments.tune_study``) and the summary
it prints (held-out success with Wilson intervals of the start point, Table I and what each run returned; the
returned parameters against the start; gradient diagnostics; the selection's validations; the best run of a study).
The options and their checks, which build the :class:`hyqjax.studies.tune.wallclock.WallClockConfig`, are
:mod:`hyqjax.cli.tune`'s (the study's further options: ``experiments/tune_study.py``).
"""
from __future__ import annotations

import os

#: Exit status of a study stopped at the end of a segment (``--segment-minutes``): sysexits' EX_TEMPFAIL, "try
#: again later" (the same command resumes it).
PAUSED = 75


def returned_lines(out: str, res: dict) -> list[str]:
    """The closing lines of a complete `hyqjax tune` run into ``out`` (results ``res``): the commands that run
    what it returned, on the step-down and on held-out step-downs, and the one that keeps it as a preset."""
    key = next(iter(res["runs"]), "")
    run = "" if len(res["runs"]) == 1 else f":{key}"
    return [f"run what it returned: hyqjax stepdown --params {out}/results.json --heights 0.24 --instances 4; "
            f"on held-out step-downs: python -m experiments.reach_map --tuned-run returned:{out}/results.json:"
            f"{key} --variants returned --spread wide",
            f"keep it as a preset (then --preset NAME in stepdown, sweep, tune and the reach map): "
            f"hyqjax presets save NAME --from {out}/results.json{run}"]


def run(args) -> int:
    """Run the tuner or the equal-wall-clock study (``args.wallclock_config``, built by :func:`hyqjax.cli.tune.validate`
    under the run directory's lock) and print its summary."""
    from hyqjax.studies.tune import figure, wallclock, wallclock_results

    cfg = args.wallclock_config
    what = "equal-wall-clock study" if args.study else ("quick tuner" if args.quick else "tuner")
    print(f"hyqjax tune: {what}: methods {list(cfg.methods)}, parameterisations {list(cfg.dims)}, budget "
          f"{' '.join(f'{m:g}' for m in cfg.wall_minutes)} min each, out {args.out}", flush=True)
    from hyqjax.io import phases

    clock = phases.current()
    clock.lap("startup")
    res = wallclock.run_wallclock_study(cfg, args.out, log=lambda s: print(s, flush=True),
                                        checkpoint_every_s=args.state_every_s, segment_minutes=args.segment_minutes)
    if res.get("paused"):
        print(f"paused at {res['paused']} after --segment-minutes {args.segment_minutes:g}; run the same command to "
              f"go on (state in {args.out})", flush=True)
        clock.lap("tuning")
        print(clock.line(), flush=True)
        return PAUSED
    clock.lap("tuning")
    fig = figure.plot_wallclock(res, os.path.join(args.out, "tuning.png"))
    clock.lap("figures")
    print(figure.wallclock_markdown(res))
    ho = res["heldout"]
    f = lambda h: (f"clean {h['clean']:.3f} [{h['clean_ci95'][0]:.3f}, {h['clean_ci95'][1]:.3f}], "  # noqa: E731
                   f"completed {h['completed']:.3f} [{h['completed_ci95'][0]:.3f}, {h['completed_ci95'][1]:.3f}]")
    n = res["heldout_set"]["instances"]
    print(f"held-out ({n} instances): start point {f(ho['start'])}; Table I, paper crawl {f(ho['table1'])}")
    for m in cfg.methods:
        for d in cfg.dims:
            k = wallclock_results.member_key(m, d, 60.0 * cfg.wall_minutes[-1])
            if k in ho:
                print(f"held-out ({n} instances): {k} (returned) {f(ho[k])}")
    if not args.study:
        from hyqjax.studies.tune import schedule

        m, d = cfg.methods[0], cfg.dims[0]
        par = schedule.make(d, cfg.groups)
        from hyqjax.studies.tune.wallclock_config import start_point, start_theta

        start = par.describe(start_theta(par, start_point(cfg)))
        got = res["runs"][f"{m}/{d}"]["params"]
        print("returned parameters (start in brackets): " + ", ".join(
            f"{k} {got[k]:.4g} ({start[k]:.4g})" for k in got if k in start))
        if got.get("stability_number", 0.0) >= 1.0:
            print(f"note: the returned reflex gains have stability number {got['stability_number']:.3g} >= 1, outside "
                  f"the step-size condition ReflexParams.validate(dt) enforces (the batched rollouts above ran them; "
                  f"reflex_step with concrete parameters refuses them; docs/tuning.md)")
    for d, g in res.get("diagnostics", {}).items():
        print(f"gradient on {d}: SNR across windows at the start mean {g['snr_mean']:.2f} (share > 2: "
              f"{g['snr_above_2']:.2f}); Spearman correlation of the window objective with held-out clean success "
              f"over {len(g['iterates'])} iterates: {g['objective_vs_heldout_spearman']:.2f} (useful: clearly < 0)")
        if g.get("step_cost"):
            print(wallclock_results.step_cost_line(d, g["step_cost"], res["config"].get("grad_mode", "jacfwd")))
    for key, r in res["runs"].items():
        if r["method"] == "guided_es" and r["log"]:
            from hyqjax.studies.tune.study.guided import cosine_summary

            c = cosine_summary(r["log"])
            slope = [x["descent_slope"] for x in r["log"] if x.get("descent_slope") is not None]
            line = (f"guided ES {key}: {c['generations']} generations; the population's slope along the surrogate's "
                    f"descent direction: positive in {sum(v > 0 for v in slope)} of {len(slope)}")
            if c["cos_search"] is not None:
                line += (f"; cosine with the search direction: median {c['cos_search']['median']:+.3f} (first third "
                         f"{c['cos_search']['first_third']:+.3f}, last third {c['cos_search']['last_third']:+.3f})")
            print(line)
        if r["method"] == "blend" and r["log"]:
            from hyqjax.studies.tune.blend import summary as blend_summary

            b = blend_summary(r["log"])
            if b["alpha"] is not None:
                print(f"blend {key}: {b['steps']} steps; alpha median {b['alpha']['median']:.3f} (the variances "
                      f"alone: {b['alpha_var']['median']:.3f}; bias guard active in {b['guard_share']:.2f} of steps)"
                      + (f"; cosine of the surrogate gradient with the zero-order estimate: median "
                         f"{b['cos']['median']:+.3f}" if b["cos"] else ""))
        if r["method"] in ("ipop_cma_es", "bipop_cma_es") and r["log"]:
            from hyqjax.studies.tune.restarts import summary as restart_summary

            rs = restart_summary(r["log"])
            print(f"restarts of {key}: {len(rs['runs'])} runs: " + "; ".join(
                f"{x['regime']} population {x['popsize']} for {x['generations']} generations ({x['ended']})"
                for x in rs["runs"]))
        fin = r.get("final_reevaluation")
        if fin:
            row = fin["candidates"][fin["chosen"]]
            print(f"final re-evaluation of {key}: {len(fin['candidates'])} candidates on {fin['instances']} further "
                  f"scenarios ({fin['wall_s']:.0f} s after the budget); returned iteration {row['iteration']}, clean "
                  f"{row['validation_clean']:.3f} on the validation batch, {row['final_clean']:.3f} on the further "
                  f"one")
        sel = r.get("selection")
        if sel and sel["log"]:
            pt = r["points"][-1]
            it = pt.get("selected_iteration", 0)
            what = (f"iteration {it}" if it else "the start point" + (f" (preset {cfg.start_preset})"
                                                                       if cfg.start_preset else "")
                    + ", which no validated iterate beat")
            print(f"selection of {key}: {len(sel['log'])} validations on {sel['instances']} fixed scenarios "
                  f"({sel['wall_s']:.0f} s, {sel['physics_steps']:,} physics steps of its budget); returned: "
                  f"{what}, validation clean {pt.get('validation_clean', float('nan')):.3f}")
    w = wallclock_results.winner(res, cfg.wall_minutes[-1])
    if args.study and w and not w["others"]:
        print(f"only run at {cfg.wall_minutes[-1]:g} min: {w['method']} / {w['dim']} (clean {w['clean']:.3f}; no other "
              f"method or parameterisation in this directory to compare with)")
    elif args.study and w:
        print(f"best at {cfg.wall_minutes[-1]:g} min: {w['method']} / {w['dim']} (clean {w['clean']:.3f}; 95% interval "
              f"{'clear of' if w['clear_of_all_others'] else 'overlapping'} the other {w['others']} runs')")
    print(f"wrote {args.out}/results.json and {fig} ({res['wall_s']:.0f} s), complete: {res['complete']}")
    if res["complete"] and not args.study:
        for line in returned_lines(args.out, res):
            print(line)
    clock.lap("summary")
    print(clock.line(), flush=True)
    return 0
