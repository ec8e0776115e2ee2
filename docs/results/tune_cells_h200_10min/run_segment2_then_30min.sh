# issue 22: one lease on 4 x H200: the 10-minute cells' second segment on all four GPUs, then, on the same four GPUs
# once those have finished, the first 13-minute segment of the 30-minute cells. The jobs never share a GPU, so each
# run's clock measures the same machine as the cells it is compared with.
bash docs/results/tune_cells_h200_10min/run_segment2.sh
bash docs/results/tune_cells_h200_10min/run_30min_segment1.sh
echo done > /tmp/done_all
