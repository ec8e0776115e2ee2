# bounding: the envelope at 512 instances per command (lateral 0), so that a command's Wilson upper bound can fall below 1 %
# (on the device, with PYTHONPATH naming the repository and the installed wheels)
mkdir -p out/e512
E="python -m experiments.bounding_envelope --speeds -1.0 1.2 0.2 --yaw-rates -1.0 1.0 0.25 --lateral-speeds 0.0 --instances 512 --seed 2 --impl warp --out out/e512"
timeout 420 $E --params robust_8s --friction 0.5 1.0 --payload 0 10 --name robust_8s_heldout_dist > out/e512/a.log 2>&1; echo $? > out/e512/a.rc
timeout 420 $E --friction 0.5 1.0 --payload 0 10 --name default_heldout_dist > out/e512/b.log 2>&1; echo $? > out/e512/b.rc
timeout 420 $E --params robust_8s --name robust_8s_wide > out/e512/c.log 2>&1; echo $? > out/e512/c.rc
echo done > out/e512/done
