# issue 22: the second segment of the four 30-minute cells whose first 13-minute segment ran in the lease of
# ../tune_cells_h200_10min/run_segment2_then_30min.sh (run_30min_segment1.sh): the same commands, without
# --segment-minutes, on copies of the directories it left (segment1/: results.json and each run's stored state,
# partial/). Each run goes on from its stored state and clock (775-779 s of its 1,800 s budget), then runs the
# held-out evaluation at 3, 10 and 30 minutes. About 19 minutes per cell, one GPU each, cells side by side.
# Arguments: the cells to run, as method:dims (default: all four), one GPU each, in the order given:
#   bash run_segment2.sh cma_es:shared random_search:shared      # a lease of two GPUs
#   bash run_segment2.sh cma_es:per_leg snes:per_leg
CELLS=${*:-cma_es:shared random_search:shared cma_es:per_leg snes:per_leg}
mkdir -p /tmp/src28 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src28/
cd /tmp/src28
export PYTHONPATH=/tmp/src28:/tmp/site
Q=/tmp/q28; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 30 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --state-every-s 30"
tune() {  # method dims gpu
  local m=$1 d=$2 g=$3
  cp -r docs/results/tune_cells_h200_30min/segment1/${m}_${d}_30min $Q/${m}_${d}_30min
  CUDA_VISIBLE_DEVICES=$g timeout 1560 $C --methods $m --dims $d --out $Q/${m}_${d}_30min > $Q/${m}_${d}_30min.seg2.log 2>&1
  echo $? > $Q/${m}_${d}_30min.seg2.rc
}
g=0
for cell in $CELLS; do
  tune ${cell%%:*} ${cell##*:} $g &
  g=$((g + 1))
done
wait
echo done > $Q/done
