# issue 22: the second segment of run_segment1.sh's four 10-minute cells: the same commands on copies of the
# directories the first segment left (segment1/: results.json and each run's stored state, partial/), so each run
# goes on from its stored state and clock (about 420 s of its 600 s budget) and then runs the held-out evaluation.
mkdir -p /tmp/src26 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src26/
cd /tmp/src26
export PYTHONPATH=/tmp/src26:/tmp/site
Q=/tmp/q26; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --state-every-s 30"
tune() {  # method dims gpu
  local m=$1 d=$2 g=$3
  cp -r docs/results/tune_cells_h200_10min/segment1/${m}_$d $Q/${m}_$d
  CUDA_VISIBLE_DEVICES=$g timeout 1020 $C --methods $m --dims $d --out $Q/${m}_$d > $Q/${m}_$d.seg2.log 2>&1
  echo $? > $Q/${m}_$d.seg2.rc
}
tune random_search per_leg 0 &
tune open_es per_leg 1 &
tune random_search per_leg_cond_all 2 &
tune open_es per_leg_cond_all 3 &
wait
echo done > $Q/done
