# round 19 (issue 23): on seed 10101 (the depth-gated probe's fresh seed, 2,048 draws per height: the same instances),
# the default crawl, --remedy, the no-reflex baseline and the recommended configuration at 14-30 cm on the wide
# spread under MuJoCo Warp, and the recommended configuration under MJX-JAX (1,024 draws, 10 heights: 10,240 runs)
mkdir -p /tmp/src19 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src19/
cd /tmp/src19
export PYTHONPATH=/tmp/src19:/tmp/site
Q=/tmp/q19; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
NG=$(wc -l < $Q/gpus.txt)
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
SR=docs/results/tune_reach_h200_10min/snes/results.json
P=edge_probe=0.1,edge_tilt=0.3,edge_margin=0.1,edge_lowering=0.01,edge_deep=0.255,edge_tilt_deep=0.5
REC="snes_reach_probe_deep:$SR:snes:$P"
H="0.14 0.16 0.18 0.20 0.22 0.24 0.26 0.27 0.28 0.30"
warp_main() {
  CUDA_VISIBLE_DEVICES=$1 timeout 570 python -m experiments.reach_map --impl warp --instances 2048 --seed 10101 \
    --heights $H --spread wide --variants default remedy snes_reach_probe_deep --tuned-run $REC \
    --out $Q/warp_wide > $Q/warp_wide.log 2>&1
  echo $? > $Q/warp_wide.rc
}
jax_rec() {
  CUDA_VISIBLE_DEVICES=$1 timeout 570 python -m experiments.reach_map --impl jax --instances 1024 --seed 10101 \
    --heights $H --spread wide --variants snes_reach_probe_deep --tuned-run $REC \
    --out $Q/jax_wide > $Q/jax_wide.log 2>&1
  echo $? > $Q/jax_wide.rc
  CUDA_VISIBLE_DEVICES=$1 timeout 400 python -m experiments.reach_map --impl warp --instances 2048 --seed 10101 \
    --heights $H --spread wide --variants paper_off --out $Q/warp_paper_off > $Q/warp_paper_off.log 2>&1
  echo $? > $Q/warp_paper_off.rc
}
if [ "$NG" -ge 2 ]; then
  warp_main 0 &
  jax_rec 1 &
  wait
else
  warp_main 0
  jax_rec 0
fi
echo done > $Q/done
