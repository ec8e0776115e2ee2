# round 18 (issue 23): the depth-gated probe on the tuned SNES gains, on a fresh seed (10101): the probe settings
# of round 17 plus edge_deep=0.255, edge_tilt_deep=0.5 (chosen on the CPU screen, seed 9494); wide 18-28 cm at
# 2,048 runs per cell (h90 needs every height below), narrow 22-27 cm at 1,024
mkdir -p /tmp/src18 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src18/
cd /tmp/src18
export PYTHONPATH=/tmp/src18:/tmp/site
mkdir -p /tmp/q18
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q18/gpus.txt
NG=$(wc -l < /tmp/q18/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > /tmp/q18/env.log 2>&1
T=docs/results
S1=$T/tune_repeats_h100_10min/snes_s1/results.json
SR=$T/tune_reach_h200_10min/snes/results.json
P=edge_probe=0.1,edge_tilt=0.3,edge_margin=0.1,edge_lowering=0.01,edge_deep=0.255,edge_tilt_deep=0.5
V="--variants snes_reach_probe_deep snes_s1_probe_deep --tuned-run snes_reach_probe_deep:$SR:snes:$P --tuned-run snes_s1_probe_deep:$S1:snes:$P"
wide() {
  CUDA_VISIBLE_DEVICES=$1 timeout 400 python -m experiments.reach_map --impl warp --instances 2048 --seed 10101 \
    --heights 0.18 0.20 0.22 0.24 0.26 0.27 0.28 --spread wide $V --out /tmp/q18/wide > /tmp/q18/wide.log 2>&1
  echo $? > /tmp/q18/wide.rc; rm -rf /tmp/q18/wide/chunks
}
narrow() {
  CUDA_VISIBLE_DEVICES=$1 timeout 400 python -m experiments.reach_map --impl warp --instances 1024 --seed 10101 \
    --heights 0.22 0.24 0.26 0.27 --spread narrow $V --out /tmp/q18/narrow > /tmp/q18/narrow.log 2>&1
  echo $? > /tmp/q18/narrow.rc; rm -rf /tmp/q18/narrow/chunks
}
if [ "$NG" -ge 2 ]; then
  wide 0 &
  narrow 1 &
  wait
else
  wide 0
  narrow 0
fi
echo done > /tmp/q18/done
