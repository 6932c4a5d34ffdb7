"""The teacher's networks: a decentralised actor and a critic (centralised for two robots)
over [normalised observation | stage one-hot], with a PopArt value head."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase
from torchrl.modules import MultiAgentMLP, PopArtValueNorm, ProbabilisticActor, TanhNormal

from pnp.losses.distributions import TanhNormalGripper
from pnp.task import ACTION_NAMES
from pnp.training.keys import ACTION, LOC, LOG_PROB, OBS, SCALE, STAGE_ONE_HOT, VALUE
from pnp.training.stage_ensemble import StageEnsemble, call_head

GRASP_ENTRY = ACTION_NAMES.index("grasp")
PER_STAGE = ("none", "bendikas", "erskine")  # model.per_stage


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

    def std(self) -> torch.Tensor:
        return self.var.sqrt().clamp(min=1e-2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) / self.std()).clamp(-self.clip, self.clip)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).to(self.mean.device).double()  # a CPU step into a GPU run's statistics
        n, mean, var = x.shape[0], x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.fill_(total)


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
        return call_head(self.head, self.mlp(x), stage)


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
    for net in [m for n in nets for m in getattr(n, "members", [n])]:  # a StageEnsemble: each member
        w, b = net.mlp.params["0", "weight"], net.mlp.params["0", "bias"]
        per_agent = w.shape[-1] // net.n_agents if net.centralised else w.shape[-1]
        for start in range(0, w.shape[-1], per_agent):  # [obs | stage] per agent when centralised
            cols = start + idx
            b += w[..., cols] @ const.to(w)
            w[..., cols] = 0.0
    obs_norm.mean[idx], obs_norm.var[idx] = 0.0, 1.0
    return idx.tolist()


class ScaleBounds(nn.Module):
    """Bounds on the policy's pre-tanh std, per action entry, around a param extractor.

    Why the floor: PPO moves the mean by a fraction of the std per iteration, so an entry
    whose std has collapsed barely moves; a sharpened warm start keeps exploring. Why the
    ceiling: with no entropy term two dual-robot runs grew the std from ~0.4 to 1-42 and
    every squashed command became a coin flip between its bounds.
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


class GripperFloor(nn.Module):
    """A soft floor under the Bernoulli gripper's logit, ``lo + softplus(logit - lo)`` with
    ``lo = logit(min_prob)``: p never falls below ``min_prob``, can still go to 1, and the
    gradient never vanishes. Optionally, in ``open_stages`` only, a soft ceiling
    ``hi - softplus(hi - .)`` with ``hi = logit(1 - open_min_prob)``.

    Why: the gripper explores by its Bernoulli draw alone. From random weights the
    ``grab_action`` term (1 - p while nothing is held) drove p to ~0 in S1 while the EE sat
    within grasp range half of the time, so closing was never tried (docs/history/pipeline_single.md).
    No ceiling elsewhere: a held box is dropped by a single open draw. Where the box has been
    put down (S5) a held box drove p to ~0.9998 and opening was never tried either.
    """

    takes_stage = True

    def __init__(self, extractor: nn.Module, index: int, min_prob: float, coeff: float = 0.0,
                 open_min_prob: float = 0.0, open_stages: tuple[int, ...] = ()):
        super().__init__()
        self.extractor, self.index, self.coeff = extractor, index, float(coeff)
        self.lo = math.log(min_prob / (1.0 - min_prob))
        self.hi = math.log((1.0 - open_min_prob) / open_min_prob) if open_min_prob > 0 else None
        self.open_stages = list(open_stages)
        self._excess: torch.Tensor | None = None

    def forward(self, x: torch.Tensor, stage: torch.Tensor | None = None):
        loc, scale = self.extractor(x)
        g = loc[..., self.index]  # the raw logit; ``loc`` is copied before the write below
        out = self.lo + nn.functional.softplus(g - self.lo)
        at = None
        if self.hi is not None:
            if stage is None:
                raise ValueError("GripperFloor with open_min_prob > 0 needs the stage one-hot")
            at = stage[..., self.open_stages].sum(-1) > 0
            out = torch.where(at, self.hi - nn.functional.softplus(self.hi - out), out)
        loc = loc.clone()
        loc[..., self.index] = out
        # Beyond a bound the soft bound's gradient vanishes and the logit drifts (-31 measured
        # below the floor), so the penalty keeps the logit near its bounds (losses only).
        self._excess = None
        if self.coeff > 0 and torch.is_grad_enabled():
            self._excess = torch.relu(self.lo - g)
            if at is not None:
                self._excess = self._excess + torch.where(at, torch.relu(g - self.hi), torch.zeros_like(g))
        return loc, scale

    def penalty(self) -> torch.Tensor | None:
        """``coeff`` times the mean squared excess of the last forward's logits beyond their
        bounds (below the floor; above the ceiling in ``open_stages``)."""
        return None if self._excess is None else self.coeff * self._excess.pow(2).mean()


class PopArt(nn.Module):
    """Critic head: an affine map in normalised space, read out at the real return scale.

    Why: the curriculum moves reward scales by orders of magnitude within a run (rho_j
    from mu_min = 0.1 up to mu_j = 100), so returns drift from ~1 to ~1e3. PopArt (van
    Hasselt et al. 2016) keeps the regression target at unit scale, and when its statistics
    move it rescales this head so the values it predicts stay the same ("preserving
    outputs"), which plain running return normalisation does not. Statistics move once per
    iteration (:meth:`update`), never inside the loss.

    ``width`` > 1: that many values side by side, each with its own statistics and affine
    map (Erskine et al.'s per-stage critics, whose returns differ in scale).
    """

    def __init__(self, beta: float, width: int = 1):
        super().__init__()
        self.width = int(width)
        self.stats = PopArtValueNorm(shape=self.width, beta=beta)
        self.weight = nn.Parameter(torch.ones(self.width))
        self.bias = nn.Parameter(torch.zeros(self.width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.stats.denormalize(x * self.weight + self.bias)

    @torch.no_grad()
    def update(self, targets: torch.Tensor) -> None:
        first = bool(self.stats.debiasing_term == 0)  # nothing to preserve yet
        zero = torch.zeros(self.width, device=self.weight.device)
        m0, s0 = self.stats.denormalize(zero), self.stats.scale()
        self.stats.update(targets.reshape(-1, self.width))
        if not first:
            m1, s1 = self.stats.denormalize(zero), self.stats.scale()
            self.weight.mul_(s0 / s1)
            self.bias.copy_((s0 * self.bias + m0 - m1) / s1)


@dataclass(frozen=True)
class PolicySpecs:
    """What the networks are built from: per robot, the observation width, the number of
    stages (the one-hot's width) and the action spec ``[A, n_act]``."""

    n_agents: int
    n_obs: int
    n_stages: int
    action: TensorSpec

    @classmethod
    def of(cls, env: EnvBase) -> PolicySpecs:
        obs = env.observation_spec[OBS].shape
        return cls(obs[-2], obs[-1], env.observation_spec[STAGE_ONE_HOT].shape[-1], env.full_action_spec_unbatched[ACTION])


@dataclass
class Models:
    """What :func:`make_models` builds; ``obs_norm`` is shared by actor and critic."""

    actor: ProbabilisticActor
    critic: TensorDictModule
    popart: PopArt | None
    obs_norm: ObsNorm | None

    @property
    def actor_net(self) -> AgentNet | StageEnsemble:
        return self.actor.module[0].module

    @property
    def critic_net(self) -> AgentNet | StageEnsemble:
        return self.critic.module


def dist_from_params(actor: ProbabilisticActor, td: TensorDictBase):
    """The action distribution of the loc/scale already in ``td`` (no network forward)."""
    return actor.module[-1].get_dist(td)


def _param_head(model_cfg: DictConfig, n_act: int) -> nn.Module:
    head = NormalParamExtractor(scale_mapping=f"biased_softplus_{float(model_cfg.init_scale)}")
    floor = torch.full((n_act,), float(model_cfg.min_scale))
    if model_cfg.grasp_min_scale > 0:
        if model_cfg.grasp_dist != "tanh_normal":
            raise ValueError(f"model.grasp_min_scale={model_cfg.grasp_min_scale} has no effect with "
                             f"model.grasp_dist={model_cfg.grasp_dist!r} (its gripper ignores the scale)")
        floor[GRASP_ENTRY] = max(float(floor[GRASP_ENTRY]), float(model_cfg.grasp_min_scale))
    ceiling = None
    if model_cfg.max_scale is not None:
        ceiling = torch.full_like(floor, float(model_cfg.max_scale))
        ceiling[GRASP_ENTRY] = math.inf  # the Bernoulli gripper's entry is a logit, its scale unused
        if (ceiling < floor).any():
            raise ValueError(f"model.max_scale={model_cfg.max_scale} is below model.min_scale={model_cfg.min_scale}")
    if (floor > 0).any() or ceiling is not None:
        head = ScaleBounds(head, floor, ceiling)
    if model_cfg.grasp_min_prob > 0:
        if model_cfg.grasp_dist != "bernoulli" or model_cfg.grasp_min_prob >= 0.5:
            raise ValueError(f"model.grasp_min_prob={model_cfg.grasp_min_prob} needs 0 <= p < 0.5 and "
                             f"model.grasp_dist='bernoulli' (got {model_cfg.grasp_dist!r})")
        head = GripperFloor(head, GRASP_ENTRY, model_cfg.grasp_min_prob, model_cfg.grasp_floor_coeff,
                            model_cfg.grasp_open_min_prob, tuple(model_cfg.grasp_open_stages))
    if model_cfg.grasp_open_min_prob > 0 and not (model_cfg.grasp_min_prob > 0 and model_cfg.grasp_open_min_prob < 0.5):
        raise ValueError(f"model.grasp_open_min_prob={model_cfg.grasp_open_min_prob} needs 0 < it < 0.5 and "
                         f"model.grasp_min_prob > 0 (got {model_cfg.grasp_min_prob})")
    return head


def make_models(model_cfg: DictConfig, loss_cfg: DictConfig, source: EnvBase | PolicySpecs) -> Models:
    """Decentralised actor with shared parameters; critic centralised iff there are 2 robots.
    With ``model.per_stage``, one such actor and critic per stage (:class:`StageEnsemble`).
    ``source``: the env the models act in, or its :class:`PolicySpecs`."""
    specs = source if isinstance(source, PolicySpecs) else PolicySpecs.of(source)
    n_agents, n_obs, n_stages, spec = specs.n_agents, specs.n_obs, specs.n_stages, specs.action
    n_in = n_obs + n_stages
    obs_norm = ObsNorm(n_obs) if model_cfg.obs_norm else None
    if model_cfg.per_stage not in PER_STAGE:
        raise ValueError(f"model.per_stage must be one of {PER_STAGE}, got {model_cfg.per_stage!r}")
    per_stage = model_cfg.per_stage != "none"
    if model_cfg.grasp_open_min_prob > 0 and not all(0 <= k < n_stages for k in model_cfg.grasp_open_stages):
        raise ValueError(f"model.grasp_open_stages={list(model_cfg.grasp_open_stages)}: this task has stages 0..{n_stages - 1}")
    actor_head = _param_head(model_cfg, spec.shape[-1])
    if per_stage:
        actor_net = StageEnsemble([AgentNet(n_in, 2 * spec.shape[-1], n_agents, False, model_cfg.actor_cells)
                                   for _ in range(n_stages)], obs_norm, actor_head)
    else:
        actor_net = AgentNet(n_in, 2 * spec.shape[-1], n_agents, False, model_cfg.actor_cells, obs_norm=obs_norm,
                             head=actor_head)
    dist_kwargs = {"low": spec.space.low, "high": spec.space.high}
    if model_cfg.grasp_dist == "bernoulli":
        if spec.shape[-1] != len(ACTION_NAMES):
            raise ValueError(f"model.grasp_dist='bernoulli' needs the pick-and-place action {ACTION_NAMES}; this task's "
                             f"action has {spec.shape[-1]} entries (use model.grasp_dist=tanh_normal)")
        dist_cls, dist_kwargs["gripper_index"] = TanhNormalGripper, GRASP_ENTRY
    elif model_cfg.grasp_dist == "tanh_normal":
        dist_cls = TanhNormal
    else:
        raise ValueError(f"model.grasp_dist must be 'bernoulli' or 'tanh_normal', got {model_cfg.grasp_dist!r}")
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[OBS, STAGE_ONE_HOT], out_keys=[LOC, SCALE]),
        in_keys=[LOC, SCALE], out_keys=[ACTION], distribution_class=dist_cls,
        distribution_kwargs=dist_kwargs, return_log_prob=True, log_prob_key=LOG_PROB,
    )
    if loss_cfg.value_norm not in ("popart", "none"):
        raise ValueError(f"loss.value_norm must be 'popart' or 'none', got {loss_cfg.value_norm!r}")
    values = n_stages if model_cfg.per_stage == "erskine" else 1  # Erskine: every stage's value
    popart = PopArt(float(loss_cfg.popart_beta), values) if loss_cfg.value_norm == "popart" else None
    if per_stage:
        critic_net = StageEnsemble([AgentNet(n_in, 1, n_agents, n_agents > 1, model_cfg.critic_cells)
                                    for _ in range(n_stages)], obs_norm, popart, concat=values > 1)
        if model_cfg.per_stage == "bendikas":  # sub-task 0 first; pnp.baselines.bendikas moves it on
            actor_net.route_all_to(0)
            critic_net.route_all_to(0)
    else:
        critic_net = AgentNet(n_in, 1, n_agents, n_agents > 1, model_cfg.critic_cells, head=popart, obs_norm=obs_norm)
    critic = TensorDictModule(critic_net, in_keys=[OBS, STAGE_ONE_HOT], out_keys=[VALUE])
    return Models(actor, critic, popart, obs_norm)
