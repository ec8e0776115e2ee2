# issue 22: four more 10-minute cells of the equal-wall-clock study, run as two segments (--segment-minutes): this
# first segment stops each job after 7 minutes of its process (cold compiles included) with its run's state stored;
# the same commands on the same directories go on from there in a later machine lease (run_segment2.sh).
# Seed 0, every compile cold, with selection, held-out 2,000 (seed 7777): random search and OpenES on the 56 per-leg
# coordinates (per_leg) and on the 98 coordinates (per_leg_cond_all)
mkdir -p /tmp/src25 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src25/
cd /tmp/src25
export PYTHONPATH=/tmp/src25:/tmp/site
Q=/tmp/q25; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
C="python -m experiments.tune_study --impl warp --seed 0 --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --state-every-s 30 --segment-minutes 7"
tune() {  # method dims gpu [extra options]
  local m=$1 d=$2 g=$3; shift 3
  CUDA_VISIBLE_DEVICES=$g timeout 600 $C --methods $m --dims $d "$@" --out $Q/${m}_$d > $Q/${m}_$d.seg1.log 2>&1
  echo $? > $Q/${m}_$d.seg1.rc
}
tune random_search per_leg 0 &
tune open_es per_leg 1 &
tune random_search per_leg_cond_all 2 &
tune open_es per_leg_cond_all 3 &
wait
echo done > $Q/done
