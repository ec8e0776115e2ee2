# round 14: the gradient's step cost at the study's setting (16 windows of 500 ticks; jacfwd, reverse mode with and
# without the checkpointed scan, one forward window; P = 14 and 68) on one GPU, and the gradient's bias against the
# zero-order smoothed gradient (plain, contacts from distance at 2,000 and 10,000 N/m) on the other
# a private copy of the tree (later calls re-sync the working directory)
mkdir -p /tmp/src14 && cp -r hyqjax experiments benchmarks pyproject.toml /tmp/src14/
cd /tmp/src14
export PYTHONPATH=/tmp/src14:/tmp/site
mkdir -p /tmp/q14
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q14/gpus.txt
NG=$(wc -l < /tmp/q14/gpus.txt)
python -c "import jax, mujoco; print(jax.__version__, mujoco.__version__, jax.devices())" > /tmp/q14/env.log 2>&1
cost() {
  CUDA_VISIBLE_DEVICES=$1 timeout 560 python benchmarks/bench_tune_step_cost.py --dims shared,per_leg_cond \
    --train-per-height 2 --windows-per-scenario 2 --window-ticks 500 --reps 3 --out /tmp/q14/step_cost.json \
    > /tmp/q14/step_cost.log 2>&1; echo $? > /tmp/q14/step_cost.rc
}
bias() {
  CUDA_VISIBLE_DEVICES=$1 timeout 560 python -m experiments.tune_gradient_bias --train-per-height 2 \
    --windows-per-scenario 2 --window-ticks 500 --pairs 256 --sigma 0.03 0.1 --stiffness 2000 10000 \
    --out /tmp/q14/bias.json > /tmp/q14/bias.log 2>&1; echo $? > /tmp/q14/bias.rc
}
if [ "$NG" -ge 2 ]; then
  cost 0 &
  bias 1 &
  wait
else
  cost 0
  bias 0
fi
echo done > /tmp/q14/done
