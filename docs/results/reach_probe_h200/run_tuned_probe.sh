# round 17 (issue 23): the edge-locating probe on top of the tuned SNES gains, confirmed on a fresh seed (9999):
# snes_s1 and snes_reach, each without and with the probe settings chosen on the CPU screen (seed 9494):
# edge_probe=0.1, edge_tilt=0.3, edge_margin=0.1, edge_lowering=0.01; 2,048 runs per cell, 22-27 cm
mkdir -p /tmp/src17 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src17/
cd /tmp/src17
export PYTHONPATH=/tmp/src17:/tmp/site
mkdir -p /tmp/q17
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q17/gpus.txt
NG=$(wc -l < /tmp/q17/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > /tmp/q17/env.log 2>&1
T=docs/results
S1=$T/tune_repeats_h100_10min/snes_s1/results.json
SR=$T/tune_reach_h200_10min/snes/results.json
P=edge_probe=0.1,edge_tilt=0.3,edge_margin=0.1,edge_lowering=0.01
map() {  # spread gpu
  CUDA_VISIBLE_DEVICES=$2 timeout 500 python -m experiments.reach_map --impl warp --instances 2048 --seed 9999 \
    --heights 0.22 0.24 0.26 0.27 --spread $1 --variants snes_s1 snes_s1_probe2 snes_reach snes_reach_probe2 \
    --tuned-run snes_s1:$S1:snes --tuned-run snes_s1_probe2:$S1:snes:$P \
    --tuned-run snes_reach:$SR:snes --tuned-run snes_reach_probe2:$SR:snes:$P --out /tmp/q17/$1 > /tmp/q17/$1.log 2>&1
  echo $? > /tmp/q17/$1.rc; rm -rf /tmp/q17/$1/chunks
}
if [ "$NG" -ge 2 ]; then
  map wide 0 &
  map narrow 1 &
  wait
else
  map wide 0
  map narrow 0
fi
echo done > /tmp/q17/done
