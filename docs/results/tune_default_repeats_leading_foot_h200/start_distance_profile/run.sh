# The commands that wrote this directory (2-core development VM, C MuJoCo for the mechanism runs).
OUT=docs/results/tune_default_repeats_leading_foot_h200/start_distance_profile
python -m experiments.start_distance_profile --out $OUT
python -m experiments.start_distance_profile --out $OUT/by_heading --bin-width 0.02 --split-yaw 4 --variants reach tuned_per_leg_reach run_1
python -m experiments.start_distance_profile --mode mechanism --out $OUT/mechanism
python -m experiments.start_distance_profile --mode mechanism --heights 0.18 --yaw -0.1 --out $OUT/mechanism_yaw-0.1
python -m experiments.start_distance_profile --mode mechanism --heights 0.18 --yaw 0.1 --out $OUT/mechanism_yaw+0.1
python -m experiments.start_distance_profile --mode mechanism --friction 1.0 --out $OUT/mechanism_friction1.0
python -m experiments.start_distance_profile --mode mechanism --preset tuned_per_leg_reach --out $OUT/mechanism_tuned_per_leg_reach
python -m experiments.start_distance_profile --mode mechanism --tuned-run run_1:docs/results/tune_default_repeats_leading_foot_h200/run_1/results.json:cma_es/per_leg --out $OUT/mechanism_run_1
python -m experiments.start_distance_profile --mode mechanism --heights 0.18 --payload 15 --out $OUT/mechanism_payload15
