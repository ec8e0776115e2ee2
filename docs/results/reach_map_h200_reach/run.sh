# The reach maps here were made by the same device script as the tuning runs they map:
# ../tune_reach_h200_10min/run.sh (the two tuning runs, then one reach map of each).
