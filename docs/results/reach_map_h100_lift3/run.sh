# #23: the same instances (seed 9292) for the saturating search without the lift option, and with lift + the slip-aware load
export PYTHONPATH=$PWD:/tmp/site
mkdir -p /tmp/rl3
R="shin_remedy=True,terrain_adaptation=0.8,search_forward_limit=0.10"
timeout 300 python -m experiments.reach_map --out /tmp/rl3 --impl warp --instances 1024 --seed 9292 --heights 0.22 0.24 0.26 \
  --spread wide narrow --variants remedy_fwd_0.10 remedy_fwd_0.10_lift_slip1 \
  --custom "remedy_fwd_0.10_lift_slip1:$R,search_forward_lift=1,stance_min_force=1" > /tmp/rl3/run.log 2>&1
echo $? > /tmp/rl3/rc; echo done > /tmp/rl3/done
