#!/bin/sh
# The probing step's CPU measurements (docs/stepdown.md, "Finding the edge: a probing step"), 2-core CPU, C MuJoCo.
# Each command writes OUT/reach_map.json; the JSONs here are those files (screen1..5 and confirm).
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
