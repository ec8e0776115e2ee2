# issue 22: four 10-minute cells of the equal-wall-clock study on the 56 per-leg coordinates (per_leg), four jobs on
# four GPUs at once, seed 0 (the earlier cells' seed), every compile cold, with selection, held-out 2,000 (seed 7777):
# CMA-ES, SNES, the gradient (jacfwd) and the hybrid (jacfwd)
mkdir -p /tmp/src24 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src24/
cd /tmp/src24
export PYTHONPATH=/tmp/src24:/tmp/site
Q=/tmp/q24; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait"
tune() {  # method dims gpu [extra options]
  local m=$1 d=$2 g=$3; shift 3
  CUDA_VISIBLE_DEVICES=$g timeout 1020 $C --methods $m --dims $d "$@" --out $Q/${m}_$d > $Q/${m}_$d.log 2>&1
  echo $? > $Q/${m}_$d.rc
}
tune cma_es per_leg 0 &
tune snes per_leg 1 &
tune gradient per_leg 2 &
tune hybrid per_leg 3 &
wait
echo done > $Q/done
