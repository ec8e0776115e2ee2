# round 21 (issue 22): the equal-wall-clock study's missing 10-minute cells, four jobs on four GPUs at once, seed 0
# (the 68-coordinate runs' seed), every compile cold, with selection, held-out 2,000 (seed 7777):
#  68 coordinates (per_leg_cond): random search, SNES, OpenES; 98 coordinates (per_leg_cond_all): CMA-ES
mkdir -p /tmp/src21 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src21/
cd /tmp/src21
export PYTHONPATH=/tmp/src21:/tmp/site
Q=/tmp/q21; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
NG=$(wc -l < $Q/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait"
tune() {  # method dims gpu
  CUDA_VISIBLE_DEVICES=$3 timeout 960 $C --methods $1 --dims $2 --out $Q/${1}_$2 > $Q/${1}_$2.log 2>&1
  echo $? > $Q/${1}_$2.rc
}
if [ "$NG" -ge 4 ]; then
  tune random_search per_leg_cond 0 &
  tune snes per_leg_cond 1 &
  tune open_es per_leg_cond 2 &
  tune cma_es per_leg_cond_all 3 &
  wait
elif [ "$NG" -ge 2 ]; then
  tune random_search per_leg_cond 0 &
  tune snes per_leg_cond 1 &
  wait
else
  tune random_search per_leg_cond 0
fi
echo done > $Q/done
