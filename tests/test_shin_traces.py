"""experiments.stepdown_shin_traces: the shin-contact replay finds a shin on the platform exactly when one touches it
(C MuJoCo forward kinematics on recorded poses; no JAX program is compiled)."""
import numpy as np

from experiments import stepdown_shin_traces as st
from hyqjax.sim import model as hmodel
from hyqjax.studies import stepdown


def test_replay_reports_the_first_shin_contact_and_nothing_while_standing():
    h = 0.24
    m = hmodel.model_spec(platform_height=h).compile()
    stand = stepdown.start_qpos(hmodel.standing_qpos(m), np.float64(0.3), np.float64(0.0), np.float64(0.0), h)
    sunk = stand.copy()
    sunk[2] -= 0.3  # the trunk 30 cm lower: the shins pass through the platform's top
    qpos = np.stack([stand, stand, sunk])
    time_s = np.array([0.0, 0.01, 0.02])
    feet_x = np.tile(np.arange(4.0), (3, 1))
    assert st.first_shin_contacts(m, qpos[:2], time_s[:2], feet_x[:2]) == {}
    first = st.first_shin_contacts(m, qpos, time_s, feet_x)
    assert set(first) == set(st.LEGS)
    assert all(v["time"] == 0.02 and v["feet_x"] == [0.0, 1.0, 2.0, 3.0] for v in first.values())


def test_bad_options_are_one_line_before_any_run(capsys):
    for argv, word in ((["--instances", "0"], "--instances"), (["--starts", "0.2", "0.1"], "--starts"),
                       (["--impl", "cuda"], "impl"), (["--crawl", "search_forward_lift=3"], "search_forward_lift")):
        assert st.main(argv + ["--out", "/tmp/hyqjax_unused"]) == 2
        err = capsys.readouterr().err
        assert word in err and err.count("\n") == 1, err
