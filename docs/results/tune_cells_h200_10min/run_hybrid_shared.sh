# round 22 (issue 22): the hybrid on the 14 shared coordinates at 10 minutes, seed 0 (the H200 runs of CMA-ES and
# random search at seed 0: docs/results/tune_wallclock_h200_10min), every compile cold, with selection, held-out 2,000
mkdir -p /tmp/src22 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src22/
cd /tmp/src22
export PYTHONPATH=/tmp/src22:/tmp/site
Q=/tmp/q22; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
timeout 900 python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 \
  --cold-compile --wait --methods hybrid --dims shared --out $Q/hybrid_shared > $Q/hybrid_shared.log 2>&1
echo $? > $Q/hybrid_shared.rc
echo done > $Q/done
