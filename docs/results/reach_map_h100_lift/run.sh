# #23: the reach map of the forward search counted from the lift-off (search_forward_lift), a fresh seed (9292), both spreads
export PYTHONPATH=$PWD:/tmp/site
mkdir -p /tmp/rl
R="shin_remedy=True,terrain_adaptation=0.8"
timeout 420 python -m experiments.reach_map --out /tmp/rl --impl warp --instances 1024 --seed 9292 --heights 0.22 0.24 0.26 \
  --spread wide narrow --variants remedy start remedy_lift remedy_lift_a0.65 remedy_fwd_0.10_lift \
  --custom "remedy_lift:$R,search_forward_lift=1" \
  --custom "remedy_lift_a0.65:shin_remedy=True,terrain_adaptation=0.65,search_forward_lift=1" \
  --custom "remedy_fwd_0.10_lift:$R,search_forward_limit=0.10,search_forward_lift=1" > /tmp/rl/run.log 2>&1
echo $? > /tmp/rl/rc; echo done > /tmp/rl/done
