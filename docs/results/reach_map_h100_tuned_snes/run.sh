# This map is the second of the two that docs/results/reach_map_h100_tuned_cma/run.sh makes side by side on two
# GPUs (seed 9393: SNES seed 1 and the 26 cm recommendation); run that script.
