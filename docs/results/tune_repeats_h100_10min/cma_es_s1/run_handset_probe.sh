# round 20 (issue 22): the edge-probe presets on the tuning study's 2,000 held-out step-downs (seed 7777, 14-30 cm,
# start 0-15 cm, friction 0.4-1.0, payload 0-15 kg), the study's own forward program (MuJoCo Warp): is a hand-set
# configuration with the probe better than the default tuner's result?
mkdir -p /tmp/src20 && cp -r hyqjax experiments benchmarks docs pyproject.toml /tmp/src20/
cd /tmp/src20
export PYTHONPATH=/tmp/src20:/tmp/site
Q=/tmp/q20; mkdir -p $Q
nvidia-smi --query-gpu=name --format=csv,noheader > $Q/gpus.txt
python -c "import jax, mujoco, warp; print(jax.__version__, mujoco.__version__, warp.__version__, jax.devices())" > $Q/env.log 2>&1
cp -r docs/results/tune_repeats_h100_10min/cma_es_s1 $Q/cma_es_s1
( time timeout 560 python -m experiments.tune_handset $Q/cma_es_s1 --presets start remedy_probe remedy_probe2 remedy_probe_deep start_probe_deep ) > $Q/handset.log 2>&1
echo $? > $Q/handset.rc
echo done > $Q/done
