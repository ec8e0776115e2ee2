# round 16 (issue 23), MuJoCo Warp, fresh seeds:
#  (1) the held-out GPU check of the edge-locating probe: remedy and the probe presets at 22-27 cm, wide and narrow
#      spreads, 1,024 runs per cell, seed 9797;
#  (2) h90 by its Wilson bound: the SNES runs (seed 1 trained at 16-28 cm; the reach objective) at 4,096 runs per
#      cell on the wide spread, 18-28 cm, seed 9898
mkdir -p /tmp/src16 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src16/
cd /tmp/src16
export PYTHONPATH=/tmp/src16:/tmp/site
mkdir -p /tmp/q16
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q16/gpus.txt
NG=$(wc -l < /tmp/q16/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > /tmp/q16/env.log 2>&1
probe() {
  CUDA_VISIBLE_DEVICES=$1 timeout 560 python -m experiments.reach_map --impl warp --instances 1024 --seed 9797 \
    --heights 0.22 0.24 0.26 0.27 --spread wide narrow --variants remedy remedy_probe remedy_probe2 --out /tmp/q16/probe > /tmp/q16/probe.log 2>&1
  echo $? > /tmp/q16/probe.rc; rm -rf /tmp/q16/probe/chunks
}
h90() {
  T=docs/results
  CUDA_VISIBLE_DEVICES=$1 timeout 560 python -m experiments.reach_map --impl warp --instances 4096 --seed 9898 \
    --heights 0.18 0.20 0.22 0.24 0.26 0.27 0.28 --spread wide --variants snes_s1 snes_reach \
    --tuned-run snes_s1:$T/tune_repeats_h100_10min/snes_s1/results.json:snes \
    --tuned-run snes_reach:$T/tune_reach_h200_10min/snes/results.json:snes --out /tmp/q16/h90 > /tmp/q16/h90.log 2>&1
  echo $? > /tmp/q16/h90.rc; rm -rf /tmp/q16/h90/chunks
}
if [ "$NG" -ge 2 ]; then
  probe 0 &
  h90 1 &
  wait
else
  probe 0
  h90 0
fi
echo done > /tmp/q16/done
