"""Adam (optax) on ``theta`` with logging, checkpoints, resume and a simulation-budget count.

``run_adam(step_fn, theta0, cfg, out_dir)`` calls ``step_fn(theta) -> dict(loss, grad, ...)`` (the
closed-loop ``jacfwd`` of :mod:`.objective`, or the kinematic surrogate's ``value_and_grad``) ``cfg.steps``
times. Per step ``log.jsonl`` gets the loss, its terms, the gradient norm, the across-window gradient
spread (when the step function returns per-window gradients), ``theta``, the parameter values, the
physics steps spent so far and the wall time; ``checkpoint.npz`` (``theta``, Adam state, step) is written
atomically every ``checkpoint_every`` steps and at the end. The same call on the same directory resumes;
a larger ``steps`` continues; another configuration (hash of everything except ``steps``) is refused.
Non-finite gradients skip the update (``optax.apply_if_finite``). A ``tqdm`` bar shows the ETA.

With ``line_search`` (scales ``c_1..c_K``) a step is Adam with backtracking: the Adam update ``u`` is a
direction, ``theta + c_k u`` are evaluated in one batch and the best is taken only if it lowers the
objective below its value at ``theta``; otherwise ``theta`` stays (Adam's moments still advance). The
objective on the fixed training windows then never rises, whatever the bias of the pathwise gradient.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.io.atomic import atomic_write, dumps


@dataclasses.dataclass(frozen=True)
class AdamConfig:
    steps: int = 40
    lr: float = 0.1
    clip: float = 1.0
    checkpoint_every: int = 5
    #: backtracking on the Adam update: the step tries ``theta + c u`` for every ``c`` here (one batched forward
    #: evaluation) and moves to the best only if it lowers the objective; empty: plain Adam
    line_search: tuple = ()

    def __post_init__(self):
        for k, lo, hi in (("steps", 0, 100000), ("checkpoint_every", 1, 100000)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if not (0.0 < self.lr <= 1.0):
            raise ValueError(f"lr must be in (0, 1], got {self.lr}")
        if not (0.0 < self.clip <= 1e3):
            raise ValueError(f"clip must be in (0, 1000], got {self.clip}")
        if any(not (0.0 < float(c) <= 10.0) for c in self.line_search) or len(self.line_search) > 16:
            raise ValueError(f"line_search must be at most 16 scales in (0, 10], got {self.line_search}")


def make_optimizer(cfg: AdamConfig):
    import optax

    return optax.apply_if_finite(optax.chain(optax.clip_by_global_norm(cfg.clip), optax.adam(cfg.lr)), 10)


def config_hash(d: dict) -> str:
    d = {k: v for k, v in d.items() if k not in ("steps", "checkpoint_every")}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


def save_checkpoint(path: str, step: int, theta, opt_state, spent: int, chash: str) -> None:
    leaves = jax.tree_util.tree_leaves(opt_state)
    arrays = {f"opt/{i:04d}": np.asarray(v) for i, v in enumerate(leaves)}
    arrays.update(theta=np.asarray(theta), step=np.asarray(step), spent=np.asarray(spent), config_hash=np.asarray(chash))
    atomic_write(path, lambda f: np.savez(f, **arrays))


def load_checkpoint(path: str, cfg: AdamConfig, chash: str):
    with np.load(path) as z:
        if str(z["config_hash"]) != chash:
            raise RuntimeError(f"{path} belongs to a different tuning configuration; use another --out")
        theta = jnp.asarray(z["theta"])
        leaves = [jnp.asarray(z[k]) for k in sorted(k for k in z.files if k.startswith("opt/"))]
        step, spent = int(z["step"]), int(z["spent"])
    treedef = jax.tree_util.tree_structure(make_optimizer(cfg).init(theta))
    return step, theta, jax.tree_util.tree_unflatten(treedef, leaves), spent


def read_log(out_dir: str) -> list[dict]:
    path = os.path.join(out_dir, "log.jsonl")
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return [json.loads(ln) for ln in f if ln.strip()]


def run_adam(step_fn: Callable, theta0, cfg: AdamConfig, out_dir: str, config: dict, cost_per_step: int,
             describe: Callable | None = None, stop_after: int | None = None, progress: bool = True,
             on_step: Callable | None = None, evaluate: Callable | None = None) -> dict:
    """Adam on ``theta`` (see the module docstring). ``config`` is the run's full configuration (hashed);
    ``cost_per_step`` its physics steps per step (line-search evaluations included); ``describe(theta) ->
    dict`` the parameter values; ``on_step(step, theta, spent)`` is called after every step (e.g. to
    snapshot for a budget curve); ``evaluate(thetas (N, P)) -> (N,)`` objective values, for
    ``cfg.line_search``. Returns ``dict(step, theta, spent, log)``."""
    if cfg.line_search and evaluate is None:
        raise ValueError("line_search needs an evaluate function")
    import optax
    from tqdm.auto import tqdm

    os.makedirs(out_dir, exist_ok=True)
    chash = config_hash(config)
    cpath, ckpt, lpath = (os.path.join(out_dir, n) for n in ("config.json", "checkpoint.npz", "log.jsonl"))
    if os.path.exists(cpath):
        with open(cpath) as f:
            old = json.load(f).get("hash", "?")
        if old != chash:
            raise RuntimeError(f"{out_dir} holds a tuning run of another configuration (hash {old[:12]} != "
                               f"{chash[:12]}); use another --out or remove it")
    atomic_write(cpath, lambda f: f.write(json.dumps(dict(config=config, hash=chash), indent=1, default=str).encode()))
    opt = make_optimizer(cfg)
    if os.path.exists(ckpt):
        step, theta, opt_state, spent = load_checkpoint(ckpt, cfg, chash)
    else:
        step, theta, spent = 0, jnp.asarray(theta0), 0
        opt_state = opt.init(theta)
    lines = [dumps(r, indent=None) + "\n" for r in read_log(out_dir) if r["step"] < step]
    atomic_write(lpath, lambda f: f.write("".join(lines).encode()))
    update = jax.jit(lambda g, s, th: opt.update(g, s, th))
    end = cfg.steps if stop_after is None else min(cfg.steps, step + stop_after)
    bar = tqdm(total=cfg.steps, initial=step, unit="step", desc="tune", disable=not progress, dynamic_ncols=True)
    t0 = time.time()
    try:
        with open(lpath, "a") as log:
            while step < end:
                r = step_fn(theta)
                g = jnp.asarray(r["grad"], theta.dtype)
                upd, opt_state = update(g, opt_state, theta)
                rec = dict(step=step, loss=float(r["loss"]), grad_norm=float(jnp.linalg.norm(g)),
                           grad=[float(x) for x in np.asarray(g)], theta=[float(x) for x in np.asarray(theta)],
                           terms={k: float(v) for k, v in r.get("terms", {}).items()}, spent=spent + cost_per_step,
                           wall_s=round(time.time() - t0, 3))
                if "per_window_grad" in r:
                    pw, ok = np.asarray(r["per_window_grad"], np.float64), np.asarray(r["ok"], bool)
                    rec["windows_ok"], rec["windows"] = int(ok.sum()), int(ok.size)
                    if ok.sum() > 1:
                        rec["grad_std"] = [float(x) for x in pw[ok].std(0, ddof=1)]
                if describe is not None:
                    rec["params"] = describe(theta)
                if cfg.line_search:
                    scales = jnp.asarray(cfg.line_search, theta.dtype)
                    cands = theta[None] + scales[:, None] * jnp.asarray(upd, theta.dtype)[None]
                    vals = np.asarray(evaluate(cands), np.float64)
                    vals = np.where(np.isfinite(vals), vals, np.inf)
                    i = int(np.argmin(vals))
                    accept = bool(vals[i] < rec["loss"])
                    rec["line_search"] = dict(scales=[float(c) for c in cfg.line_search],
                                              losses=[float(v) if np.isfinite(v) else None for v in vals],
                                              chosen=float(cfg.line_search[i]) if accept else 0.0)
                    theta = cands[i] if accept else theta
                else:
                    theta = optax.apply_updates(theta, upd)
                spent += cost_per_step
                log.write(dumps(rec, indent=None) + "\n")  # strict JSON lines (non-finite -> null)
                log.flush()
                step += 1
                bar.update(1)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", gnorm=f"{rec['grad_norm']:.3g}")
                if step % cfg.checkpoint_every == 0 or step == end:
                    save_checkpoint(ckpt, step, theta, opt_state, spent, chash)
                if on_step is not None:
                    on_step(step, np.asarray(theta), spent)
    finally:
        bar.close()
    return dict(step=step, theta=np.asarray(theta), spent=spent, log=read_log(out_dir))
