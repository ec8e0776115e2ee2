# This map is the second of the two that docs/results/reach_map_h100_tuned_fresh/run.sh makes (seed 9393, the
# eight other 10-minute runs at 24/26/28 cm, both spreads); run that script.
