#!/bin/sh
# The probing step's CPU measurements (docs/stepdown.md, "Finding the edge: a probing step"), 2-core CPU, C MuJoCo.
# Each command writes OUT/reach_map.json; the JSONs here are those files (screen1..8, confirm, confirm2, confirm3).
R=shin_remedy=True,terrain_adaptation=0.8,edge_probe=0.1
# screen, seed 9494, wide spread, 24 cm (the same 96 instances for every variant)
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread wide --out out/screen1 \
  --variants remedy probe probe_t30 probe_t50 probe_t30_m10 \
  --custom probe:$R,edge_tilt=0.8 --custom probe_t30:$R,edge_tilt=0.3 --custom probe_t50:$R,edge_tilt=0.5 \
  --custom probe_t30_m10:$R,edge_tilt=0.3,edge_margin=0.1
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread wide --out out/screen2 \
  --variants probe_t30_m20 probe_t30_m10_lift probe_t40_m10 \
  --custom probe_t30_m20:$R,edge_tilt=0.3,edge_margin=0.2 \
  --custom probe_t30_m10_lift:$R,edge_tilt=0.3,edge_margin=0.1,search_forward_lift=1 \
  --custom probe_t40_m10:$R,edge_tilt=0.4,edge_margin=0.1
# the other cells, seed 9494: narrow 24 cm, wide 22 and 26 cm
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread narrow --out out/screen3 \
  --variants remedy probe_t30_m10 --custom probe_t30_m10:$R,edge_tilt=0.3,edge_margin=0.1
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.22 0.26 --spread wide --out out/screen4 \
  --variants remedy probe_t30_m10 --custom probe_t30_m10:$R,edge_tilt=0.3,edge_margin=0.1
# confirmation on a fresh seed, 256 instances, wide spread, 24 cm
python -m experiments.reach_map --impl c --instances 256 --seed 9696 --heights 0.24 --spread wide --out out/confirm \
  --variants remedy probe_t30_m10 --custom probe_t30_m10:$R,edge_tilt=0.3,edge_margin=0.1

# Using the estimate: the trunk's height while a front hip is behind the edge (edge_lowering), and the other uses of
# the bounds that were screened and dropped (docs/stepdown.md, "Using the estimate"). P: remedy_probe's settings.
P=$R,edge_tilt=0.3,edge_margin=0.1
# screen, seed 9494, wide 24 cm: trunk lowered 1-3 cm while a front hip is behind (screen5.json)
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread wide --out out/screen5 \
  --variants lo01 lo02 lo02_t40 lo03_m15 \
  --custom lo01:$P,edge_lowering=0.01 --custom lo02:$P,edge_lowering=0.02 \
  --custom lo02_t40:$R,edge_tilt=0.4,edge_margin=0.1,edge_lowering=0.02 \
  --custom lo03_m15:$R,edge_tilt=0.3,edge_margin=0.15,edge_lowering=0.03
# the same with step_down_lowering (the trunk lower throughout the step down; screen6.json)
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread wide --out out/screen6 \
  --variants pl05 pl08 --custom pl05:$P,step_down_lowering=0.05 --custom pl08:$P,step_down_lowering=0.08
# the other cells for lo01, seed 9494 (screen7.json: narrow 24 cm; screen8.json: wide 22 and 26 cm)
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.24 --spread narrow --out out/screen7 \
  --variants probe_lo01 --custom probe_lo01:$P,edge_lowering=0.01
python -m experiments.reach_map --impl c --instances 96 --seed 9494 --heights 0.22 0.26 --spread wide --out out/screen8 \
  --variants probe_lo01 --custom probe_lo01:$P,edge_lowering=0.01
# confirmation on the fresh seed 9696, 256 instances: 24 cm (confirm2.json; remedy and remedy_probe: confirm.json, the
# same instances) and 26 cm (confirm3.json)
python -m experiments.reach_map --impl c --instances 256 --seed 9696 --heights 0.24 --spread wide --out out/confirm2 \
  --variants probe_lo01 --custom probe_lo01:$P,edge_lowering=0.01
python -m experiments.reach_map --impl c --instances 256 --seed 9696 --heights 0.26 --spread wide --out out/confirm3 \
  --variants remedy probe_t30_m10 probe_lo01 --custom probe_t30_m10:$P --custom probe_lo01:$P,edge_lowering=0.01
# traces of remedy_probe2 (traces2/shin_traces.json)
python -m experiments.stepdown_shin_traces --height 0.24 --starts 0.01 0.04 --starts 0.11 0.14 --instances 8 \
  --crawl $P,edge_lowering=0.01 --out docs/results/reach_probe_cpu/traces2
