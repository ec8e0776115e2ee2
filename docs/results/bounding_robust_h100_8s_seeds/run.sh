# bounding: seed repeats of the robust study trained on 8 s rollouts (270 s per method), and the envelope map of robust_8s
export PYTHONPATH=$PWD:/tmp/site
mkdir -p /tmp/b26
C="python -m experiments.bounding_robust --impl warp --opt-seconds 270 --train-duration 8.0"
run() { # gpu name seed stages...
  g=$1; n=$2; s=$3; shift 3
  mkdir -p /tmp/b26/$n && cp docs/results/bounding_robust_h100/envelope_before.json /tmp/b26/$n/
  CUDA_VISIBLE_DEVICES=$g timeout 600 $C --seed $s --out /tmp/b26/$n --stages "$@" > /tmp/b26/$n.log 2>&1; echo $? > /tmp/b26/$n.rc
}
run 0 cma_s1 1 cma_es heldout &
run 1 grad_s1 1 gradient heldout &
run 2 cma_s2 2 cma_es heldout &
( CUDA_VISIBLE_DEVICES=3 timeout 200 python -m experiments.bounding_envelope --params robust_8s --speeds -1.0 1.2 0.2 \
    --yaw-rates -1.0 1.0 0.25 --lateral-speeds -0.3 0.0 0.3 --instances 64 --seed 1 --impl warp \
    --out /tmp/b26/env --name envelope_robust_8s > /tmp/b26/env.log 2>&1; echo $? > /tmp/b26/env.rc
  run 3 grad_s2 2 gradient heldout ) &
wait
echo done > /tmp/b26/done
