"""The curriculum transforms on the MuJoCo PnP env, collected with a TorchRL Collector."""
from torchrl.collectors import Collector
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pnp.envs.pnp_env import PnPEnv
from pnp.task.stage_graph import pnp_default_reward_config, pnp_default_stage_graph
from pnp.task.terms import STAGE_TERMS
from pnp.transforms import StageTransition, make_reward_schedule


def test_curriculum_on_pnp_env_in_a_collector():
    base = PnPEnv(num_worlds=3, num_robots=1, seed=0, nthread=1)
    base.max_steps = 6  # short episodes so several end inside one collection
    schedule = make_reward_schedule("dynamic", K=2.0, mu_min=0.1, **pnp_default_reward_config())
    env = TransformedEnv(base, Compose(StageTransition(pnp_default_stage_graph(), one_hot_key=("agents", "stage_one_hot")), schedule))
    check_env_specs(env)
    rho0 = None
    collector = Collector(env, policy=None, frames_per_batch=3 * 14, total_frames=3 * 14)
    for data in collector:
        rho0 = rho0 if rho0 is not None else schedule.rho.clone()
        assert data["next", "agents", "stage"].shape == (3, 14, 1, 1)
        assert data["next", "agents", "stage_one_hot"].shape == (3, 14, 1, 7)
        ended = data["next", "agents", "episode_stage"] >= 0
        assert ended.sum() >= 3 * 2  # two episodes per world ended
    collector.shutdown()
    hist = schedule.pop_stage_histogram()
    assert hist.sum() >= 6 and hist[0] >= 1  # random actions end in S0 mostly
    # Episodes ending in S0 raise S0's terms (to mu_j) and lower the others (to mu_min).
    rho = dict(zip(schedule.stage_term_names, schedule.rho.reshape(-1, len(STAGE_TERMS)).mean(0).tolist()))
    assert abs(rho["gripper_ready_pose"] - 2.0) < 1e-6 and abs(rho["object_height"] - 0.1) < 1e-6
