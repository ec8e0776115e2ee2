# the reach map (seed 9393) of the default tuner's returned parameters (CMA-ES seed 1 and SNES seed 1, 10 minutes, docs/results/tune_repeats_h100_10min), the defaults and the 26 cm recommendation; one H100 each, 2026-11-26
export PYTHONPATH=$PWD:/tmp/site
NG=2  # GPUs: the two maps ran side by side
R="shin_remedy=True,terrain_adaptation=0.8,search_forward_limit=0.10,search_forward_lift=1"
M="python -m experiments.reach_map --impl warp --instances 1024 --seed 9393 --heights 0.2 0.22 0.24 0.26 0.28 --spread wide narrow"
T=docs/results/tune_repeats_h100_10min
(CUDA_VISIBLE_DEVICES=0 timeout 400 $M --out /tmp/q11/reach_cma --variants default remedy tuned \
   --tuned $T/cma_es_s1/results.json --tuned-method cma_es > /tmp/q11/reach_cma.log 2>&1; echo $? > /tmp/q11/reach_cma.rc) &
if [ "$NG" -lt 2 ]; then wait; fi
(CUDA_VISIBLE_DEVICES=$((NG - 1)) timeout 400 $M --out /tmp/q11/reach_snes --variants tuned remedy_fwd_lift \
   --custom "remedy_fwd_lift:$R" --tuned $T/snes_s1/results.json --tuned-method snes > /tmp/q11/reach_snes.log 2>&1; echo $? > /tmp/q11/reach_snes.rc) &
wait
