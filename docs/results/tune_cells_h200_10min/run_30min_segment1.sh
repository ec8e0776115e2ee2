# issue 22: the equal-wall-clock study's 30-minute budget (checkpoints at 3, 10 and 30 minutes), four cells on four
# GPUs at once, seed 0, every compile cold, with selection, held-out 2,000 (seed 7777): CMA-ES (the default) and
# random search on the 14 shared coordinates, CMA-ES and SNES on the 56 per-leg coordinates. A 30-minute budget does
# not fit one machine lease: this first segment stops each job after 13 minutes of its process with its run's state
# stored (exit status 75); the same commands on the same directories go on from there in a later lease. It runs in
# the same lease, after run_segment2.sh (run_segment2_then_30min.sh), so that both fit one 30-minute lease.
mkdir -p /tmp/src27 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src27/
cd /tmp/src27
export PYTHONPATH=/tmp/src27:/tmp/site
Q=/tmp/q27; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 30 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --state-every-s 30 --segment-minutes 13"
tune() {  # method dims gpu
  local m=$1 d=$2 g=$3
  CUDA_VISIBLE_DEVICES=$g timeout 1500 $C --methods $m --dims $d --out $Q/${m}_${d}_30min > $Q/${m}_${d}_30min.seg1.log 2>&1
  echo $? > $Q/${m}_${d}_30min.seg1.rc
}
tune cma_es shared 0 &
tune random_search shared 1 &
tune cma_es per_leg 2 &
tune snes per_leg 3 &
wait
echo done > $Q/done
