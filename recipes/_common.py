"""Steps shared by the recipes: env + curriculum, MAPPO models, rollouts, metrics, checkpoints."""
from __future__ import annotations

import math
import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, NormalParamExtractor, TensorDictModule, set_interaction_type
from torch import nn
from torchrl.envs import Compose, StepCounter, TransformedEnv
from torchrl.modules import MultiAgentMLP, PopArtValueNorm, ProbabilisticActor, TanhNormal
from torchrl.modules.value_norm import ValueNorm
from torchrl.objectives import MAPPOLoss

from pnp.losses.distributions import TanhNormalGripper
from pnp.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES
from pnp.ee_task import ee_reward_config, ee_stage_graph
from pnp.envs.ee_tracking_env import EETrackingEnv
from pnp.envs.pnp_env import PnPEnv
from pnp.layout import START_RANGE
from pnp.stage_graph import StageGraph, pnp_default_reward_config, pnp_default_stage_graph
from pnp.task import HL_DT, ee_out_of_reach
from pnp.transforms import StageTransition, make_reward_schedule

OBS = ("agents", "observation")
STAGE_ONE_HOT = ("agents", "stage_one_hot")
ACTION = ("agents", "action")
LOG_PROB = ("agents", "action_log_prob")
VALUE = ("agents", "state_value")
LOC, SCALE = ("agents", "loc"), ("agents", "scale")
EPISODE_STAGE = ("agents", "episode_stage")
PEAK = ("agents", "stage_peak")  # present under curriculum.episode_stage=peak
GRASP_ENTRY = 7  # the grasp probability's index in the action (pnp.task.ACTION_NAMES)
N_STAGES = pnp_default_stage_graph().n_stages  # of the pick-and-place task
# env.task -> (stage graph, reward-schedule kwargs): what the curriculum needs of a task.
TASKS = {
    "pnp": (pnp_default_stage_graph, pnp_default_reward_config),
    "ee_tracking": (ee_stage_graph, ee_reward_config),
}


# --- env -----------------------------------------------------------------------------------
def _task(env_cfg: DictConfig) -> str:
    task = str(env_cfg.get("task", "pnp"))
    if task not in TASKS:
        raise ValueError(f"env.task must be one of {sorted(TASKS)}, got {task!r}")
    return task


def schedule_args(cur: DictConfig, task: str = "pnp") -> tuple[str, dict]:
    """Name and kwargs of ``make_reward_schedule`` for a ``curriculum`` config."""
    cfg = TASKS[task][1]()
    over = dict(cur.get("fixed_weights") or {})
    unknown = sorted(set(over) - set(cfg["fixed_weights"]))
    if unknown:
        raise ValueError(f"curriculum.fixed_weights names unknown terms {unknown}; the R_fixed terms of "
                         f"{task!r} are {sorted(cfg['fixed_weights'])}")
    cfg["fixed_weights"].update({k: float(v) for k, v in over.items()})
    if not cur.stage_rewards:
        # Control run: only R_fixed; every stage-wise term becomes a fixed term of weight 0.
        cfg["fixed_weights"].update({n: 0.0 for n in cfg["mu"]})
        cfg.update(term_stage={}, mu={})
        return "fixed", cfg
    cfg.update(K=float(cur.K), mu_min=float(cur.mu_min), final_after=int(cur.final_after),
               completed_floor=float(cur.get("completed_floor", 0.0)))
    return str(cur.schedule), cfg


def make_env(env_cfg: DictConfig, cur_cfg: DictConfig, seed: int) -> TransformedEnv:
    """The ``env.task`` env (``PnPEnv`` or ``EETrackingEnv``) wrapped in StepCounter ->
    StageTransition -> reward schedule."""
    task = _task(env_cfg)
    if task == "pnp":
        boxes = env_cfg.get("boxes")
        if boxes not in (None, "single", "dual"):
            raise ValueError(f"env.boxes must be null, 'single' or 'dual', got {boxes!r}")
        backend = str(env_cfg.backend)
        # Kinematic only (MuJoCo has real contacts): ignored elsewhere, so a run trained with it
        # still evaluates on MuJoCo.
        kin = {k: True for k in ("box_blocks_base", "lone_holder_pinned", "grasp_holds") if env_cfg.get(k)}
        base = PnPEnv(num_worlds=int(env_cfg.num_worlds), num_robots=int(env_cfg.num_robots),
                      backend=backend, backend_options=(kin or None) if backend == "kinematic" else None,
                      seed=int(seed), nthread=env_cfg.get("nthread"),
                      start_range=tuple(env_cfg.get("start_range") or START_RANGE),
                      grasp_sampling=str(env_cfg.get("grasp_sampling", "threshold")),
                      terminate_on_success=bool(env_cfg.get("terminate_on_success", True)),
                      handle_order=str(env_cfg.get("handle_order", "identity")),
                      handle_claim=bool(env_cfg.get("handle_claim", False)),
                      box_assets={None: None, "single": SINGLE_ROBOT_BOXES, "dual": DUAL_ROBOT_BOXES}[boxes])
    else:
        if int(env_cfg.num_robots) != 1:
            raise ValueError(f"env.task=ee_tracking has one robot, got env.num_robots={env_cfg.num_robots}")
        base = EETrackingEnv(num_worlds=int(env_cfg.num_worlds), backend=str(env_cfg.backend), seed=int(seed),
                             nthread=env_cfg.get("nthread"))
    name, sched = schedule_args(cur_cfg, task)
    return TransformedEnv(base, Compose(
        # Before StageTransition: a shorter episode limit sets done, which ends the stage.
        StepCounter(max_steps=env_cfg.get("max_episode_steps")),
        StageTransition(stage_graph(cur_cfg, task), one_hot_key=STAGE_ONE_HOT,
                        episode_stage=str(cur_cfg.get("episode_stage", "final"))),
        make_reward_schedule(name, **sched),
    ))


def stage_graph(cur_cfg: DictConfig, task: str = "pnp") -> StageGraph:
    """The task's stage graph, with ``curriculum.backward_edges`` (a list of [from, to]
    stage names or indices) in place of its own backward edges when that is set."""
    graph = TASKS[task][0]()
    edges = cur_cfg.get("backward_edges")
    if edges is None:
        return graph
    pairs = [tuple(e) for e in edges]
    bad = [e for e in pairs if len(e) != 2]
    if bad:
        raise ValueError(f"curriculum.backward_edges needs [from, to] pairs, got {bad}")
    return StageGraph(graph.stages, graph.conditions, tuple(pairs))


def schedule_of(env: TransformedEnv):
    return env.transform[-1]


# --- models ----------------------------------------------------------------------------------
class ObsNorm(nn.Module):
    """Running mean and std of the observation (Chan's parallel update), clipped to +-5.

    Positions in metres spread over ~10 m next to unit-scale flags; normalised inputs
    speed PPO up markedly. Moves only in :meth:`update`, once per iteration after the
    PPO epochs, so a batch is collected and trained on with the same statistics.
    """

    def __init__(self, n: int, clip: float = 5.0):
        super().__init__()
        self.clip = clip
        self.register_buffer("mean", torch.zeros(n))
        self.register_buffer("var", torch.ones(n))
        self.register_buffer("count", torch.zeros(()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) / self.var.sqrt().clamp(min=1e-2)).clamp(-self.clip, self.clip)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).double()
        n, mean, var = x.shape[0], x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.fill_(total)


@torch.no_grad()
def fold_constant_inputs(obs_norm: ObsNorm, nets, tol: float = 1e-3) -> list[int]:
    """Warm start into an env where inputs that never moved now move: keep every net's
    function on the old data, but make it blind to those inputs until it learns them.

    Observation entries with running variance below ``tol`` (the kinematic backend's wrist
    roll, pad touch before any grasp) would hit the +-clip after normalisation the first
    time they change. Their first-layer weights are folded into the bias at the old
    (constant) input value and zeroed; their statistics become mean 0, variance 1.
    Returns the folded indices.
    """
    idx = (obs_norm.var < tol).nonzero().view(-1)
    if not len(idx):
        return []
    const = obs_norm(obs_norm.mean.float().unsqueeze(0))[0, idx]  # the normalised old value
    for net in nets:
        w, b = net.mlp.params["0", "weight"], net.mlp.params["0", "bias"]
        per_agent = w.shape[-1] // net.n_agents if net.centralised else w.shape[-1]
        for start in range(0, w.shape[-1], per_agent):  # [obs | stage] per agent when centralised
            cols = start + idx
            b += w[..., cols] @ const.to(w)
            w[..., cols] = 0.0
    obs_norm.mean[idx], obs_norm.var[idx] = 0.0, 1.0
    return idx.tolist()


class AgentNet(nn.Module):
    """An MLP with shared parameters over [normalised observation | stage one-hot] per agent:
    the teacher sees its stage.

    ``centralised``: agent i's input is its own block followed by the others' (in order
    i+1, i+2, ...), so every agent's output depends on all inputs but stays its own. Why
    not MultiAgentMLP(centralized=True, share_params=True): it gives all agents one shared
    value, while each robot here has its own stage and reward.
    """

    def __init__(self, n_in: int, n_out: int, n_agents: int, centralised: bool, cells, head: nn.Module | None = None,
                 obs_norm: ObsNorm | None = None):
        super().__init__()
        self.n_agents, self.centralised = n_agents, centralised and n_agents > 1
        self.obs_norm = obs_norm if obs_norm is not None else nn.Identity()
        width = n_in * n_agents if self.centralised else n_in
        self.mlp = MultiAgentMLP(n_agent_inputs=width, n_agent_outputs=n_out, n_agents=n_agents, centralized=False,
                                 share_params=True, num_cells=list(cells), activation_class=nn.Tanh)
        self.head = head if head is not None else nn.Identity()

    def forward(self, obs: torch.Tensor, stage: torch.Tensor):
        x = torch.cat([self.obs_norm(obs), stage], -1)
        if self.centralised:  # [N, A, k] -> [N, A, A*k]: own block first
            x = torch.cat([x.roll(-k, dims=-2) for k in range(self.n_agents)], -1)
        return self.head(self.mlp(x))


class ScaleBounds(nn.Module):
    """Bounds on the policy's pre-tanh std, per action entry, around a param extractor.

    Why the floor: PPO moves the mean by a fraction of the std per iteration, so an entry
    whose std has collapsed barely moves. The grasp probability needs to move from "keep
    open" to "close and hold" long after the arm's entries have sharpened
    (model.grasp_min_scale). Why the ceiling (model.max_scale): with no entropy term two
    dual-robot runs grew the std from ~0.4 to 1-42 and every squashed command became a coin
    flip between its bounds; a 1.0 ceiling held it at ~0.35, though that run lost its
    approach all the same (results/train_dual/NOTES.md).
    """

    def __init__(self, extractor: nn.Module, floor: torch.Tensor, ceiling: torch.Tensor | None = None):
        super().__init__()
        self.extractor = extractor
        self.register_buffer("floor", floor, persistent=False)  # config, not state
        self.register_buffer("ceiling", ceiling, persistent=False)

    def forward(self, x: torch.Tensor):
        loc, scale = self.extractor(x)
        scale = torch.maximum(scale, self.floor)
        return loc, scale if self.ceiling is None else torch.minimum(scale, self.ceiling)


class PopArt(nn.Module):
    """Critic head: an affine map in normalised space, read out at the real return scale.

    Why: the curriculum moves reward scales by orders of magnitude within a run (rho_j
    from mu_min = 0.1 up to mu_j = 100), so returns drift from ~1 to ~1e3. PopArt (van
    Hasselt et al. 2016) keeps the regression target at unit scale, and when its statistics
    move it rescales this head so the values it predicts stay the same ("preserving
    outputs"), which plain running return normalisation does not. Statistics move once per
    iteration (:meth:`update`), never inside the loss.
    """

    def __init__(self, beta: float):
        super().__init__()
        self.stats = PopArtValueNorm(shape=1, beta=beta)
        self.weight = nn.Parameter(torch.ones(1))
        self.bias = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.stats.denormalize(x * self.weight + self.bias)

    @torch.no_grad()
    def update(self, targets: torch.Tensor) -> None:
        first = bool(self.stats.debiasing_term == 0)  # nothing to preserve yet
        m0, s0 = self.stats.denormalize(torch.zeros(1)), self.stats.scale()
        self.stats.update(targets.reshape(-1, 1))
        if not first:
            m1, s1 = self.stats.denormalize(torch.zeros(1)), self.stats.scale()
            self.weight.mul_(s0 / s1)
            self.bias.copy_((s0 * self.bias + m0 - m1) / s1)


class _PopArtLossNorm(ValueNorm):
    """PopArt statistics seen by MAPPOLoss, read-only (they move in ``PopArt.update``)."""

    def __init__(self, popart: PopArt):
        super().__init__(shape=1)
        self.__dict__["popart"] = popart  # not a submodule: its state lives in the critic

    def update(self, value_target):
        pass

    def normalize(self, value_target):
        return self.popart.stats.normalize(value_target)

    def denormalize(self, normalised_value):
        return self.popart.stats.denormalize(normalised_value)

    def scale(self):
        return self.popart.stats.scale()


def make_models(model_cfg: DictConfig, env: TransformedEnv, value_norm: str, popart_beta: float):
    """Decentralised actor with shared parameters; critic centralised iff there are 2 robots."""
    base = env.base_env
    n_agents = base.num_robots
    n_obs = env.observation_spec[OBS].shape[-1]
    n_in = n_obs + env.observation_spec[STAGE_ONE_HOT].shape[-1]
    spec = env.full_action_spec_unbatched[ACTION]
    obs_norm = ObsNorm(n_obs) if model_cfg.obs_norm else None  # one instance, shared by actor and critic
    head = NormalParamExtractor(scale_mapping=f"biased_softplus_{float(model_cfg.init_scale)}")
    floor = torch.full((spec.shape[-1],), float(model_cfg.get("min_scale", 0.0)))
    floor[GRASP_ENTRY] = max(float(floor[GRASP_ENTRY]), float(model_cfg.get("grasp_min_scale", 0.0)))
    ceiling = None
    if model_cfg.get("max_scale") is not None:
        ceiling = torch.full_like(floor, float(model_cfg.max_scale))
        ceiling[GRASP_ENTRY] = math.inf  # the Bernoulli gripper's entry is a probability, not a std
        if (ceiling < floor).any():
            raise ValueError(f"model.max_scale={model_cfg.max_scale} is below the std floor {floor.max().item()}")
    if (floor > 0).any() or ceiling is not None:
        head = ScaleBounds(head, floor, ceiling)
    actor_net = AgentNet(n_in, 2 * spec.shape[-1], n_agents, False, model_cfg.actor_cells, obs_norm=obs_norm,
                         head=head)
    dist_kwargs = {"low": spec.space.low, "high": spec.space.high}
    # Checkpoints from before the Bernoulli gripper have no key: they are TanhNormal throughout.
    grasp_dist = str(model_cfg.get("grasp_dist", "tanh_normal"))
    if grasp_dist == "bernoulli":
        dist_cls, dist_kwargs["gripper_index"] = TanhNormalGripper, GRASP_ENTRY
    elif grasp_dist == "tanh_normal":
        dist_cls = TanhNormal
    else:
        raise ValueError(f"model.grasp_dist must be 'bernoulli' or 'tanh_normal', got {grasp_dist!r}")
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[OBS, STAGE_ONE_HOT], out_keys=[LOC, SCALE]),
        in_keys=[LOC, SCALE], out_keys=[ACTION], distribution_class=dist_cls,
        distribution_kwargs=dist_kwargs, return_log_prob=True, log_prob_key=LOG_PROB,
    )
    popart = PopArt(popart_beta) if value_norm == "popart" else None
    critic_net = AgentNet(n_in, 1, n_agents, n_agents > 1, model_cfg.critic_cells, head=popart, obs_norm=obs_norm)
    critic = TensorDictModule(critic_net, in_keys=[OBS, STAGE_ONE_HOT], out_keys=[VALUE])
    return actor, critic, popart, obs_norm


def make_loss(loss_cfg: DictConfig, actor, critic, popart: PopArt | None) -> MAPPOLoss:
    loss = MAPPOLoss(
        actor, critic, value_norm=_PopArtLossNorm(popart) if popart is not None else None,
        clip_epsilon=float(loss_cfg.clip_epsilon), entropy_coeff=float(loss_cfg.entropy_coeff),
        critic_coeff=float(loss_cfg.critic_coeff), loss_critic_type=str(loss_cfg.loss_critic_type),
        functional=False,  # PopArt rescales the critic's own parameters in place
    )
    loss.set_keys(reward=("agents", "reward"), action=ACTION, sample_log_prob=LOG_PROB, value=VALUE,
                  advantage=("agents", "advantage"), value_target=("agents", "value_target"),
                  done="done", terminated="terminated")
    loss.make_value_estimator(gamma=float(loss_cfg.gamma), lmbda=float(loss_cfg.lmbda))
    return loss


# --- data --------------------------------------------------------------------------------------
ROLL_IN = "roll_in"  # bool [N, 1] per step: the action was the policy's mean (a roll-in step)


class MeanRollIn:
    """Episodes that begin with the policy's *mean* action for a random number of steps,
    then sample as usual (a roll-in / roll-out split, as in learning-to-search).

    Why: evaluation runs the mean, and the mean has fixed points that the training noise
    escapes (a MuJoCo policy stood 10 cm short of the handle with its arm at full reach,
    LINEAGE.md), so PPO hardly ever sees those states. Rolled in on the mean, the sampled
    roll-out starts there. Roll-in actions were not drawn from the policy, so their steps
    are left out of the PPO loss (``ppo_update``); the roll-out's advantages only look ahead.

    ``share`` of episodes get a roll-in of 1..``max_steps`` steps (uniform); the others none.
    """

    def __init__(self, num_worlds: int, share: float, max_steps: int):
        if not 0.0 <= share <= 1.0 or max_steps < 1:
            raise ValueError(f"collect.roll_in_share must be in [0, 1] and collect.roll_in_max_steps >= 1, "
                             f"got {share} and {max_steps}")
        self.share, self.max_steps = share, max_steps
        self.length = torch.zeros(num_worlds, dtype=torch.long)  # roll-in steps of each world's episode

    def begin(self, new: torch.Tensor) -> None:
        """Draw roll-in lengths for the worlds whose episode starts now (bool [N])."""
        n = int(new.sum())
        if n:
            draw = torch.randint(1, self.max_steps + 1, (n,))
            self.length[new] = torch.where(torch.rand(n) < self.share, draw, 0)


def collect(env: TransformedEnv, policy, carried: TensorDictBase, steps: int,
            roll_in: MeanRollIn | None = None) -> tuple[TensorDictBase, TensorDictBase]:
    """``steps`` steps of every world from ``carried``; returns the [N, T] batch and the next carried td.

    The loop the Collector runs (step_and_maybe_reset), kept here because its carried td
    is the one piece of state a bit-for-bit resume needs and ``Collector.state_dict`` does
    not hold it (its constructor even resets the env). With ``roll_in``, steps inside an
    episode's roll-in take the mean action and are flagged ``ROLL_IN``.
    """
    out = []
    # Sampled actions: ProbabilisticActor's default interaction type is deterministic.
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        for _ in range(steps):
            carried = policy(carried)
            if roll_in is not None:
                count = carried["step_count"].reshape(-1)  # steps already taken in the episode
                roll_in.begin(count == 0)
                det = count < roll_in.length
                if det.any():
                    # From the loc/scale the policy just wrote: no second forward.
                    mean = policy.module[-1].get_dist(carried).deterministic_sample
                    carried[ACTION] = torch.where(det[:, None, None], mean, carried[ACTION])
                carried[ROLL_IN] = det.unsqueeze(-1)
            td, carried = env.step_and_maybe_reset(carried)
            out.append(td)
    return torch.stack(out, -1), carried


def episode_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Success rate, mean end-of-episode stage and stage shares of the episodes that ended."""
    nxt = batch["next"]
    done = nxt["done"].squeeze(-1)
    stage = nxt[EPISODE_STAGE]
    ended = stage[stage >= 0]
    n = int(done.sum())
    out = {"episodes": float(n), "reward": float(nxt["agents", "reward"].mean())}
    out["success_rate"] = float(nxt["success"].squeeze(-1)[done].float().mean()) if n else math.nan
    out["mean_end_stage"] = float(ended.float().mean()) if ended.numel() else math.nan
    won = nxt["success"].squeeze(-1) & done
    # Episodes that go on after success (env.terminate_on_success=false) record its step.
    out["completion_time_s"] = math.nan
    if won.any():
        steps = nxt["success_step"] if "success_step" in nxt.keys() else nxt["step_count"]
        out["completion_time_s"] = seconds(steps.squeeze(-1)[won].float().mean())
    one_hot = nxt.get(STAGE_ONE_HOT, None)  # the task's stage count (pick-and-place's if absent)
    n_stages = N_STAGES if one_hot is None else one_hot.shape[-1]
    hist = torch.bincount(ended, minlength=n_stages).float()
    for i, h in enumerate(hist):
        out[f"stage_share/S{i}"] = float(h / hist.sum()) if ended.numel() else math.nan
    if nxt.get(PEAK, None) is not None:
        # lambda(e) is the peak stage (curriculum.episode_stage=peak): log the final stage too.
        final = nxt["agents", "stage"][stage >= 0]
        out["mean_final_stage"] = float(final.float().mean()) if final.numel() else math.nan
        fh = torch.bincount(final, minlength=n_stages).float()
        for i, h in enumerate(fh):
            out[f"final_stage_share/S{i}"] = float(h / fh.sum()) if final.numel() else math.nan
    return out


def policy_kl(actor, td: TensorDictBase) -> float:
    """Mean KL(behaviour || current) of the pre-tanh Gaussians: the TanhNormal KL, as tanh is a bijection
    (plus the gripper Bernoulli's under ``model.grasp_dist=bernoulli``)."""
    with torch.no_grad():
        new = actor.module[0](td.select(OBS, STAGE_ONE_HOT).copy())
        make_dist = actor.module[-1].get_dist  # the ProbabilisticTensorDictModule: params -> distribution
        old_d, new_d = make_dist(td.select(LOC, SCALE).detach()), make_dist(new.select(LOC, SCALE))
    if isinstance(old_d, TanhNormalGripper):
        return float(old_d.kl_to(new_d).mean())
    mu0, s0, mu1, s1 = td[LOC].detach(), td[SCALE].detach(), new[LOC], new[SCALE]
    kl = torch.log(s1 / s0) + (s0**2 + (mu0 - mu1) ** 2) / (2 * s1**2) - 0.5
    return float(kl.sum(-1).mean())


def reach_loss(actor, td: TensorDictBase) -> torch.Tensor:
    """Mean distance (m) of the policy's *mean* EE command beyond the arm's reach
    (``pnp.task.ee_out_of_reach``), differentiable in the actor's parameters.

    Why a loss and not only a reward (``curriculum.fixed_weights.ee_out_of_reach``): the
    MuJoCo policy's mean EE x command sits at 1.29 of the 1.3 bound, where the tanh's slope
    is ~2 % of its peak, so sampled actions barely move it and a -50 / m reward left the
    excess unchanged after 118 iterations (mean 0.20 m in S0). Measured with coefficient
    10: the excess fell to 0.04 m, but the gradient went mostly into the unsaturated y, z
    entries, moving the executed command; training success fell from 0.78 to 0.45.
    """
    params = actor.module[0](td.select(OBS, STAGE_ONE_HOT).copy())
    mean = actor.module[-1].get_dist(params.select(LOC, SCALE)).deterministic_sample
    return ee_out_of_reach(mean[..., 3:6]).mean()


def seconds(steps) -> float:
    return float(steps) * HL_DT


# --- checkpoints and RNG ---------------------------------------------------------------------------
def rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def save_checkpoint(path: Path, payload: dict) -> None:
    """Atomic: a run killed while writing keeps its previous checkpoint."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, weights_only=False, map_location="cpu")  # our own files


def resolve_checkpoint(spec, runs_root: str | Path) -> Path:
    """``true``/``latest``: the newest ``checkpoint.pt`` under ``runs_root``; a run folder; or a file."""
    if spec is True or str(spec).lower() in ("true", "latest"):
        found = sorted(Path(runs_root).glob("**/checkpoint.pt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise FileNotFoundError(f"no checkpoint.pt under {Path(runs_root).resolve()}")
        return found[-1]
    path = Path(str(spec))
    if path.is_dir():
        path = path / "checkpoint.pt"
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    return path
