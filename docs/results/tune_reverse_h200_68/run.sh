# round 15: issue 22's remaining device measurements, four jobs on four GPUs in parallel:
#  GPU0/1: the gradient step's cost at the study's setting (16 windows x 500 ticks), P = 14 and P = 68 separately
#  GPU2/3: the gradient and the hybrid with --grad-mode reverse on 68 coordinates, 3 and 10 minutes, held-out 2000
mkdir -p /tmp/src15 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src15/
cd /tmp/src15
export PYTHONPATH=/tmp/src15:/tmp/site
mkdir -p /tmp/q15
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q15/gpus.txt
NG=$(wc -l < /tmp/q15/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > /tmp/q15/env.log 2>&1
cost() {  # dim gpu
  CUDA_VISIBLE_DEVICES=$2 timeout 570 python benchmarks/bench_tune_step_cost.py --dims $1 \
    --train-per-height 2 --windows-per-scenario 2 --window-ticks 500 --reps 3 --out /tmp/q15/step_cost_$1.json \
    > /tmp/q15/step_cost_$1.log 2>&1; echo $? > /tmp/q15/step_cost_$1.rc
}
C="python -m experiments.tune_study --impl warp --dims per_leg_cond --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --grad-mode reverse"
tune() {  # method gpu
  CUDA_VISIBLE_DEVICES=$2 timeout 900 $C --methods $1 --out /tmp/q15/${1}_rev68 > /tmp/q15/${1}_rev68.log 2>&1; echo $? > /tmp/q15/${1}_rev68.rc
}
if [ "$NG" -ge 4 ]; then
  cost shared 0 &
  cost per_leg_cond 1 &
  tune gradient 2 &
  tune hybrid 3 &
  wait
elif [ "$NG" -ge 2 ]; then
  (cost shared 0; cost per_leg_cond 0) &
  tune hybrid 1 &
  wait
else
  tune hybrid 0
fi
echo done > /tmp/q15/done
