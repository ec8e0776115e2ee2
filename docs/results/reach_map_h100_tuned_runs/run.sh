# round 12: the reach of the tuners' returned parameters. A: a fresh seed (9595) for the two runs chosen on seed 9393
# (CMA-ES seed 1, SNES seed 1) with the defaults, at 20-28 cm including 27 cm; B: every other 10-minute run on 9393
export PYTHONPATH=$PWD:/tmp/site
mkdir -p /tmp/q12
T=docs/results/tune_repeats_h100_10min
M="python -m experiments.reach_map --impl warp --instances 1024 --spread wide narrow"
timeout 500 $M --out /tmp/q12/reach_fresh --seed 9595 --heights 0.2 0.22 0.24 0.26 0.27 0.28 \
  --variants default remedy cma_s1 snes_s1 \
  --tuned-run cma_s1:$T/cma_es_s1/results.json:cma_es --tuned-run snes_s1:$T/snes_s1/results.json:snes \
  > /tmp/q12/reach_fresh.log 2>&1; echo $? > /tmp/q12/reach_fresh.rc
(cd /tmp && tar czf /tmp/q12_partial.tgz q12)
R=""
V=""
for s in 2 3 4 5 6 7; do R="$R --tuned-run cma_s$s:$T/cma_es_s$s/results.json:cma_es"; V="$V cma_s$s"; done
for s in 2 3; do R="$R --tuned-run snes_s$s:$T/snes_s$s/results.json:snes"; V="$V snes_s$s"; done
timeout 500 $M --out /tmp/q12/reach_runs --seed 9393 --heights 0.24 0.26 0.28 --variants $V $R \
  > /tmp/q12/reach_runs.log 2>&1; echo $? > /tmp/q12/reach_runs.rc
rm -rf /tmp/q12/reach_*/chunks
echo done > /tmp/q12/done
