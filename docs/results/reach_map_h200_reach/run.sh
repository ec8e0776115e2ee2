# round 13: the reach as the tuning objective: CMA-ES and SNES (seed 1, 10 minutes, cold compiles, selection) trained
# at 24-30 cm on the wide spread; held-out 2,000 (seed 7777) as every other run; then the reach map of each result
# on the fresh seed 9595 (the seed of the earlier maps of default, remedy, cma_s1, snes_s1)
# a private copy of the tree (later calls re-sync the working directory), with the committed versions of files
# being edited elsewhere
mkdir -p /tmp/src13 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src13/
cp -r .devrun/snap13/hyqjax/. /tmp/src13/hyqjax/
rm -f /tmp/src13/hyqjax/sim/reverse_mode.py
cd /tmp/src13
export PYTHONPATH=/tmp/src13:/tmp/site
mkdir -p /tmp/q13
nvidia-smi --query-gpu=name --format=csv,noheader > /tmp/q13/gpus.txt
NG=$(wc -l < /tmp/q13/gpus.txt)
C="python -m experiments.tune_study --impl warp --dims shared --wall-minutes 3 10 --heldout 2000 --heldout-chunk 4 --cold-compile --wait --seed 1 --train-heights 0.24,0.26,0.28,0.30 --train-spread wide"
M="python -m experiments.reach_map --impl warp --instances 1024 --spread wide narrow --seed 9595 --heights 0.24 0.26 0.27 0.28 0.29 0.30"
one() {  # method gpu
  CUDA_VISIBLE_DEVICES=$2 $C --methods $1 --out /tmp/q13/${1}_reach > /tmp/q13/${1}_reach.log 2>&1; echo $? > /tmp/q13/${1}_reach.rc
  (cd /tmp && tar czf /tmp/q13_partial_$1.tgz q13/${1}_reach q13/${1}_reach.log)
  CUDA_VISIBLE_DEVICES=$2 timeout 420 $M --out /tmp/q13/map_$1 --variants ${1}_reach \
    --tuned-run ${1}_reach:/tmp/q13/${1}_reach/results.json:$1 > /tmp/q13/map_$1.log 2>&1; echo $? > /tmp/q13/map_$1.rc
  rm -rf /tmp/q13/map_$1/chunks
}
if [ "$NG" -ge 2 ]; then
  one cma_es 0 &
  one snes 1 &
  wait
else
  one cma_es 0
fi
echo done > /tmp/q13/done
