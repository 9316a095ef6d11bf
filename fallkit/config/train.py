"""`train:` — PPO and the networks (paper Table III), and fallkit's measured changes to learn faster.

The Table III values are the defaults; where fallkit's defaults differ from the paper
(the joint prior, its fade and a pull toward it, the critic's own rate without value clipping and
with a value per reward term and a shorter GAE λ for the orientation term, the actor observing u(t),
bfloat16 products) docs/training.md gives the
paired measurement, and `train=paper` sets the paper's setting exactly.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from fallkit.config.section import Section

# The orientation term's own GAE λ in the default (with a value per term). Its advantage is the actor's
# noisiest (std ~6 a step against ~2 for the impact's): paid at the landing, decided early in the
# fall; λ 0.8 halved that spread (MROE and max impact lower or equal on seeds 0-3 against 0.95), and
# λ 0.6 cut it to ~2.6 with MROE lower than 0.8's on every seed 0-3; λ 0.4 with train=quick's 1024
# worlds (~2.0) put max impact and MROE lower than 0.6 with 256 on 4 of 5 seeds (docs/training.md). A dict so the
# per-term default reads as the option's own value.
DEFAULT_TERM_LAM: dict[str, float] = {"orientation": 0.4}


class PPOConfig(Section):
    """Table III; `learning_rate` is the starting point of the actor's adaptive (KL) rule."""

    num_minibatches: int = Field(4, gt=0)
    late_num_minibatches: int | None = Field(
        None,
        gt=0,
        description="from late_from_env_steps on, the update's minibatch count instead of num_minibatches: many "
        "small steps while the policy learns to soften the fall, fewer bigger ones (a larger sample per step, a "
        "higher rate the KL rule allows) once it learns to steer; null = num_minibatches throughout (docs/training.md)",
    )
    late_from_env_steps: int = Field(
        6_000_000, ge=0, description="env steps (all worlds, all ranks) after which late_num_minibatches applies"
    )
    epochs: int = Field(5, gt=0)
    clip: float = Field(0.2, gt=0)
    entropy_coef: float = Field(0.0, ge=0)
    gamma: float = Field(0.99, gt=0, le=1)
    lam: float = Field(0.95, ge=0, le=1)
    desired_kl: float | None = Field(0.01, gt=0, description="null = fixed learning rate")
    kl_stop: float | None = Field(
        None, gt=1, description="the actor's steps end for the rest of an update at the first minibatch whose KL to "
        "the collecting policy passes kl_stop × desired_kl, its rate set to lr_min, where the rule's remaining steps "
        "would take it (and the policy hardly moves); the critic's steps go on (fallkit.rl.ppo). null = every "
        "minibatch steps both (rsl_rl, the paper). Reads the KL on the host at every minibatch",
    )
    learning_rate: float = Field(1e-3, gt=0)
    lr_min: float = Field(1e-5, gt=0)
    lr_max: float = Field(1e-2, gt=0)
    max_grad_norm: float = Field(1.0, gt=0)
    clip_per_network: bool = Field(
        False,
        description="clip the actor's and the critic's gradients to max_grad_norm each by its own norm; false = one "
        "clip over both (rsl_rl, the paper), where the critic's norm (10-200x the actor's) sets the actor's scale",
    )
    value_coef: float = Field(1.0, ge=0)
    value_clip: float | None = Field(
        None, gt=0, description="clip of the value prediction's change per update (rsl_rl's clipped value loss); null = off"
    )
    critic_learning_rate: float | None = Field(
        1e-3,
        gt=0,
        description="the critic's own fixed Adam rate; null = the actor's KL-adaptive rate (rsl_rl, the paper)",
    )
    normalize_value: bool = Field(
        False,
        description="the critic predicts values in units of the running mean and std of the value targets (the "
        "loss too), its last layer rescaled as they move (PopArt's preserving step; fallkit.rl.models.ValueNet)",
    )
    orientation_potential: float = Field(
        0.0,
        ge=0,
        description="c of a potential-based shaping of the orientation term for PPO's advantages, F = γΦ(s') − "
        "Φ(s) with Φ = −c‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖²: credit for the tilt gained or lost toward the end pose when it "
        "happens, the task's optimal policies unchanged (fallkit.rl.shaping); 0 = off",
    )
    mirror: bool = Field(
        False,
        description="left-right symmetry augmentation: every minibatch also trains on its mirror image (mirrored "
        "observations and actions, same advantage; fallkit.env.mirror). Only for robots whose derived mirror map "
        "exists (RobotSpec.mirror_map); off until a paired learning run shows it pays (docs/training.md)",
    )
    relabel_sensitivity: bool = Field(
        False,
        description="with env.sensitivity_inputs: every minibatch also trains on its samples under other drawn "
        "weights, the impact repriced by (w'/w)² per component (the weights only price the forces, so the falls "
        "are the same; fallkit.rl.relabel), so each sample contrasts two weightings of its action; off until a "
        "paired run shows it pays (docs/sensitivity_inputs.md)",
    )
    relabel_end_pose: bool = Field(
        False,
        description="every minibatch also trains on its samples under another end pose drawn from the training "
        "set, the orientation and joint terms recomputed for it (the end pose changes nothing in the physics; "
        "fallkit.rl.relabel), so each fall also teaches how good it was for another goal; off until a paired "
        "learning run shows it pays (docs/training.md)",
    )
    value_per_term: bool = Field(
        True,
        description="a decomposed critic: one value head per reward term (impact, orientation, ...), each fitted to "
        "its own term's returns by its own GAE; the actor's advantage is their sum, so the task is unchanged and each "
        "head learns a simpler function than the whole return (fallkit.rl.ppo; measured on three seeds, "
        "docs/training.md); false: one value for the whole return (the paper)",
    )
    term_lam: dict[str, float] = Field(
        default_factory=lambda: dict(DEFAULT_TERM_LAM),
        description="with value_per_term: a GAE λ of its own for some reward terms, the others keep `lam`. The "
        "default gives the orientation term λ 0.4: paid late (blended in by u(t)) and decided early, its "
        "advantage is the actor's noisiest, and the shorter λ trades a little bias for less than half its spread (measured "
        "in docs/training.md). Set one with `train.ppo.term_lam.orientation=0.9` (another term: "
        "`+train.ppo.term_lam.<term>=`); null = `lam` for every term. With one value for the whole return "
        "(value_per_term=false) the default is dropped: that critic has one λ",
    )
    term_gamma: dict[str, float] = Field(
        default_factory=dict,
        description="with value_per_term: a discount γ of its own for some reward terms (`+train.ppo.term_gamma."
        "orientation=0.995`), the others keep `gamma`; the orientation term is paid late and, at the time limit, "
        "bootstrapped from its head, so its own γ sets how much the landing's tilt weighs at the moment the fall's "
        "side is decided; {} = `gamma` for all (measured in docs/training.md)",
    )
    prior_coef: float = Field(
        0.03,
        ge=0,
        description="β of a penalty β·Σ_j d_j² on the learned deviation d (the MLP's share of the policy mean, in "
        "action units) of the collected samples: a pull toward the joint prior (train.prior), which already lands "
        "the falls it can land; needs a prior; 0 = off (train=paper). 0.03: both impact figures lower on three of "
        "four paired seeds, steering unchanged (docs/training.md)",
    )
    value_per_component: bool = Field(
        False,
        description="with value_per_term: the impact term's value split further, one head per robot component (its "
        "sensitivity-weighted impact alone), so the critic tells apart which part hits; with env.sensitivity_inputs "
        "each such head is scaled by the observed w_c² (fallkit.rl.models.ValueNet), so it learns the unweighted "
        "return; off until a paired run shows it pays (docs/training.md, docs/sensitivity_inputs.md)",
    )

    @model_validator(mode="after")
    def _rate_range(self) -> PPOConfig:
        # the KL rule clamps only the rate it has just changed, so a start outside the range or an
        # empty range would run at a rate the user never asked for
        if self.desired_kl is not None and not self.lr_min <= self.learning_rate <= self.lr_max:
            raise ValueError(
                f"train.ppo.learning_rate={self.learning_rate:g} must lie in [lr_min, lr_max] = "
                f"[{self.lr_min:g}, {self.lr_max:g}], the range of the KL-adaptive rate: change one of the three"
            )
        if self.kl_stop is not None and self.desired_kl is None:
            raise ValueError(
                f"train.ppo.kl_stop={self.kl_stop:g} is a multiple of desired_kl, which is null (a fixed rate): "
                "set train.ppo.desired_kl or drop kl_stop"
            )
        return self

    def minibatches_at(self, env_steps: int) -> int:
        """The update's minibatch count after `env_steps` env steps of training (late_num_minibatches' schedule)."""
        late = self.late_num_minibatches is not None and env_steps >= self.late_from_env_steps
        return self.late_num_minibatches if late else self.num_minibatches

    def per_term(self, option: str, terms: list[str]) -> dict[str, float]:
        """`term_lam` or `term_gamma` for a run with these reward terms: the default's λ only where its term is
        (reward.orientation=0 drops the term); a term the user named is kept, for the caller to refuse."""
        default = DEFAULT_TERM_LAM if option == "term_lam" else {}  # term_gamma has no per-term default
        return {t: v for t, v in getattr(self, option).items() if t in terms or default.get(t) != v}

    @field_validator("term_lam", "term_gamma", mode="before")
    @classmethod
    def _none_is_empty(cls, value: object) -> object:
        return {} if value is None else value  # `train.ppo.term_lam=null`: a Hydra merge cannot empty a dict

    @model_validator(mode="after")
    def _per_component_needs_per_term(self) -> PPOConfig:
        if not self.value_per_term and self.term_lam == DEFAULT_TERM_LAM:
            self.term_lam = {}  # the default belongs to the value per term; one value has one λ
        if self.value_per_component and not self.value_per_term:
            raise ValueError("train.ppo.value_per_component=true needs train.ppo.value_per_term=true (a value per term)")
        for option, symbol in (("term_lam", "λ"), ("term_gamma", "γ")):
            if getattr(self, option) and not self.value_per_term:
                raise ValueError(
                    f"train.ppo.{option} needs train.ppo.value_per_term=true (a {symbol} per term, a value per term)"
                )
        bad = {k: v for k, v in self.term_lam.items() if not 0.0 <= v <= 1.0}
        if bad:
            name, v = next(iter(bad.items()))
            raise ValueError(f"train.ppo.term_lam.{name}={v}: a GAE λ lies in [0, 1]")
        bad = {k: v for k, v in self.term_gamma.items() if not 0.0 < v < 1.0}
        if bad:  # γ = 1 is refused: time-limit truncation bootstraps the tail, which would then never end
            name, v = next(iter(bad.items()))
            raise ValueError(f"train.ppo.term_gamma.{name}={v}: a term's discount lies in (0, 1)")
        return self


class LevelReplayConfig(Section):
    """Prioritised replay of training falls (fallkit.env.samplers.replay; PLR, Jiang et al. 2021)."""

    share: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="share of the restarting training worlds that replay a stored fall (its initial state and end "
        "pose) chosen by its score, the mean |advantage| of its last play, instead of drawing a fresh one; 0: every "
        "fall fresh (the paper). Evaluation is unaffected",
    )
    score: str = Field(
        "advantage",
        description="what scores a play, as the mean of its absolute value over the play's steps: 'advantage' (the "
        "actor's, PLR's L1 value loss) or a reward term's own advantage (needs train.ppo.value_per_term), e.g. "
        "orientation: the falls whose landing side the actor can still change",
    )
    size: int = Field(1024, ge=1, description="stored falls; replay starts once the buffer is full")
    temperature: float = Field(
        0.1, gt=0, description="a stored fall is replayed with weight (1/rank of its score)^(1/temperature) (PLR's 0.1)"
    )
    staleness: float = Field(
        0.1, ge=0, le=1, description="share of the replay chance given by how long ago a fall was last played (PLR's 0.1)"
    )


class SelfImitationConfig(Section):
    """Self-imitation of the policy's own better-than-expected actions (fallkit.rl.self_imitation; SIL, Oh et al. 2018)."""

    steps: int = Field(
        0,
        ge=0,
        description="self-imitation minibatch steps after each PPO update, each on the loss −log π(a|s)·(R − V(s))₊/σ_A "
        "over stored steps whose discounted return R beat the critic's value (σ_A: the latest batch's advantage "
        "std); 0: off (the paper)",
    )
    term: str = Field(
        "return",
        description="what R and V are: 'return' (the whole reward and value) or one reward term's (needs "
        "train.ppo.value_per_term), e.g. orientation: imitate the actions that steered better than expected",
    )
    size: int = Field(
        32_768,
        ge=1,
        description="stored steps (first in, first out); the store and the running episodes are in every checkpoint: "
        "2.2 kB per step for biped20, 160 MB per checkpoint with 256 envs",
    )
    minibatch: int = Field(1536, ge=1, description="stored steps per self-imitation step")
    learning_rate: float = Field(
        5e-5, gt=0, description="Adam rate of the self-imitation steps (the actor only; with `steps`, their strength)"
    )
    max_weight: float = Field(5.0, gt=0, description="(R − V)₊ / σ_A is clipped here, so one lucky fall cannot dominate")
    min_weight: float = Field(
        0.0,
        ge=0,
        description="a step enters the store only when (R − V) / σ_A exceeds this: with 0 about half of a dense "
        "reward's steps do; 2 keeps the few that did much better than expected, as a sparse reward would",
    )


class TeachersConfig(Section):
    """Policies trained at fixed sensitivity weights that a policy with sensitivity inputs imitates at the
    weights it draws (fallkit.rl.teachers; kickstarting, Schmitt et al. 2018; docs/sensitivity_inputs.md)."""

    runs: list[str] = Field(
        default_factory=list,
        description="trained runs (run dirs or checkpoints) of this robot without sensitivity inputs, each weighting "
        "one component at most other than this run's robot, two or more weights per such component (the robot's own "
        "counts), e.g. the head at 1 and at 4; the run draws those components' weights (env.sensitivity_inputs."
        "components=[head]; several: draw=one) and each sample imitates the mean actions of its drawn component's "
        "teachers, blended linearly in ln w between the two nearest; [] = off",
    )
    coef: float = Field(
        1.0,
        gt=0,
        description="α of the imitation term α·Σ_j (μ_j − μ̂_j)² added to PPO's loss (μ the student's mean action, "
        "μ̂ the teachers' blend, in action units, over the collected samples); PPO's own terms keep learning beside it. "
        "With two axes (draw=one) 3 read each as far as one axis alone does (docs/sensitivity_inputs.md)",
    )


class TrainConfig(Section):
    """Budget, networks, the policy's prior, logging and checkpoints of a training run."""

    iterations: int = Field(75_000, gt=0)
    num_steps: int = Field(24, gt=0, description="policy steps per env per iteration")
    max_minutes: float | None = Field(None, gt=0, description="wall-clock budget; the run checkpoints and stops")
    actor_hidden: list[int] = Field(default_factory=lambda: [512, 512, 512])
    critic_hidden: list[int] = Field(default_factory=lambda: [512, 512, 512])
    critic_layer_norm: bool = Field(
        False,
        description="LayerNorm after each hidden layer of the critic (Linear, LayerNorm, ELU), as BRO and SimBa "
        "use to keep a critic fitting moving targets; docs/training.md",
    )
    init_noise_std: float = Field(1.0, gt=0, description="initial policy std, in action units")
    prior: Literal["none", "hold", "seek"] = Field(
        "seek",
        description="policy mean = MLP + a prior setpoint (fallkit.rl.models.JointPrior): none (the paper), hold "
        "the measured joints, or seek: hold blended into the target joints by u(t) (needs env.observe_blend)",
    )
    fade_residual: bool = Field(
        True,
        description="policy mean = prior + (1 − u(t))·MLP: the learned deviation fades as the tracking blend comes "
        "in, so the end of the fall is the prior's (needs a prior and env.observe_blend)",
    )
    prior_power: float = Field(
        8.0,
        gt=0,
        description="the prior seeks and fades by u(t)^power instead of u(t): above 1 the hold and the learned "
        "deviation keep more of the fall, and the prior takes the joints to the end pose later (8: measured "
        "on two seeds against 1, docs/training.md)",
    )
    fade_noise: float | None = Field(
        None,
        gt=0,
        le=1,
        description="the exploration noise fades with the learned deviation, std·(f + (1 − f)·(1 − u(t)^power)) for "
        "this floor f: where the mean is the prior's alone the noise teaches nothing and only shakes the landing the "
        "orientation and joint terms judge (null: the same std throughout; needs train.fade_residual)",
    )
    short_episodes: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="this fraction of the training episodes ends at reward.blend_time instead of env.episode_length, "
        "truncated (the critic's value of the state there stands in for the rest, learned from the episodes that run "
        "on): with train.fade_residual the rest of a fall is the prior's alone, so those steps teach the actor "
        "nothing. Evaluation always runs to env.episode_length. 0: every episode runs to the end",
    )
    level_replay: LevelReplayConfig = Field(default_factory=LevelReplayConfig)
    self_imitation: SelfImitationConfig = Field(default_factory=SelfImitationConfig)
    noise_correlation_time: float = Field(
        0.0,
        ge=0,
        description="[s] the exploration noise is correlated in time over about this long (an AR(1) process per "
        "world, fallkit.rl.exploration): a push held for a few tenths of a second can steer a fall where "
        "independent draws at every step average out; each step's action stays N(loc, scale). 0: white noise",
    )
    precision: Literal["auto", "float32", "bfloat16"] = Field(
        "auto",
        description="arithmetic of the networks' matrix products (fallkit.rl.models.run_mlp): bfloat16 runs them "
        "under autocast with float32 weights and sums (the PPO update 1.9x as fast on a CPU with AVX512-BF16); auto "
        "= bfloat16 on such a CPU, float32 elsewhere (resolved when training starts; the checkpoint records which). "
        "Training only: a trained policy is evaluated and exported in float32",
    )
    init_from: str | None = Field(
        None,
        description="start the actor and critic from a trained policy (checkpoint or run dir): its weights, "
        "observation statistics and action std, observation parts matched by name, parts it did not observe (e.g. "
        "env.sensitivity_inputs) starting at zero weight; a new run otherwise (fallkit.rl.init_from). resume= "
        "continues a run instead",
    )
    early_reward_factor: dict[str, float] = Field(
        default_factory=dict,
        description="reward terms whose Table I weight is multiplied by this factor for the first "
        "early_until_env_steps env steps, then fades to Table I's (`train.early_reward_factor.orientation=5`; `++` "
        "where the preset sets none): steer first, soften after; the critic's heads of those terms are rescaled as "
        "the weight changes (fallkit.rl.reward_schedule, measured in docs/training.md); {} = Table I's throughout",
    )
    early_until_env_steps: int = Field(
        3_500_000, ge=0, description="env steps (all worlds, all ranks) after which early_reward_factor starts to fade"
    )
    early_fade_env_steps: int = Field(
        2_000_000,
        ge=0,
        description="env steps over which each early factor then falls linearly to 1 (Table I's weight); 0 = at once, "
        "which undid the steering the early factor bought (docs/learning_log.md)",
    )
    early_within_budget: bool = Field(
        False,
        description="true: where the run's budget (train.iterations or train.max_minutes, whichever ends it) ends "
        "before early_until_env_steps + early_fade_env_steps, the schedule is compressed to end with it, so a run "
        "ends at Table I's weights on a slower machine too (there: lower max impact, higher MROE, docs/training.md); "
        "false = by env steps alone",
    )
    teachers: TeachersConfig = Field(default_factory=TeachersConfig)
    ppo: PPOConfig = Field(default_factory=PPOConfig)
    checkpoint_every: int = Field(500, gt=0, description="iterations between checkpoints")
    evaluate: bool = Field(True, description="evaluate the final policy into the run dir")
    torch_threads: int = Field(
        0, ge=0, description="torch CPU threads of the PPO update (0 = this process's share of the cores, fallkit.machine); collection uses one beside MuJoCo's"
    )

    @field_validator("early_reward_factor", mode="before")
    @classmethod
    def _no_factors(cls, value: object) -> object:
        return {} if value is None else value  # `train.early_reward_factor=null`: a Hydra merge cannot empty a dict

    @model_validator(mode="after")
    def _factors_positive(self) -> TrainConfig:
        bad = {k: v for k, v in self.early_reward_factor.items() if not v > 0}
        if bad:  # a factor 0 would silently drop a term for a while; reward.<term>=0 drops it openly
            name, v = next(iter(bad.items()))
            raise ValueError(
                f"train.early_reward_factor.{name}={v}: a factor on a reward weight must be > 0 "
                f"(to drop the term: reward.{name}=0; to keep Table I's weight: train.early_reward_factor.{name}=1)"
            )
        if self.early_reward_factor and self.self_imitation.steps > 0:  # its store would mix two weightings' returns
            raise ValueError(
                "train.self_imitation keeps returns under the reward weights they were collected with, which "
                "train.early_reward_factor changes during the run: add train.early_reward_factor=null (train=quick sets "
                "orientation: 5)"
            )
        return self
