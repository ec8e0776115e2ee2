# issue 22: more 10-minute cells of the equal-wall-clock study, four jobs on four GPUs at once, seed 0 (the earlier
# cells' seed), every compile cold, with selection, held-out 2,000 (seed 7777):
#  14 coordinates (shared): the gradient (jacfwd), then the held-out evaluation of the stored hybrid run alone;
#  98 coordinates (per_leg_cond_all): the hybrid (jacfwd), the gradient (reverse mode), SNES
mkdir -p /tmp/src23 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src23/
cd /tmp/src23
export PYTHONPATH=/tmp/src23:/tmp/site
Q=/tmp/q23; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait"
tune() {  # method dims gpu [extra options]
  local m=$1 d=$2 g=$3; shift 3
  CUDA_VISIBLE_DEVICES=$g timeout 1020 $C --methods $m --dims $d "$@" --out $Q/${m}_$d > $Q/${m}_$d.log 2>&1
  echo $? > $Q/${m}_$d.rc
}
shared() {
  tune gradient shared 0
  cp -r docs/results/tune_cells_h200_10min/hybrid_shared $Q/hybrid_shared
  tune hybrid shared 0
}
shared &
tune hybrid per_leg_cond_all 1 &
tune gradient per_leg_cond_all 2 --grad-mode reverse &
tune snes per_leg_cond_all 3 &
wait
echo done > $Q/done
