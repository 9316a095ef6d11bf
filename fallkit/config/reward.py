"""`reward:` — weights of the reward terms (paper Table I) and the settings they need."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from fallkit import registry

# Built-in terms in Table I order; each is also the entry-point name of its function.
BUILTIN_TERMS = (
    "impact", "root_acc", "orientation", "joints", "torques", "joint_acc", "action_rate", "action_acc", "offset",
)  # fmt: skip


_SETTINGS = ("terms", "force_unit", "force_clip", "blend_time")


class RewardConfig(BaseModel):
    """Weights of the reward terms (paper Table I) and the settings they need.

    Every weight multiplies its term's unweighted value AND the policy dt (0.02 s),
    so the per-step reward is dt · Σ weight · term. Weight 0 switches a term off
    (it is not computed). Further keys name registered plugin terms and their
    weights (`+reward.my_term=2.0`); `terms` maps a term name to the registered
    function that computes it, to replace a built-in (`reward.terms.impact=my_impact`).
    """

    model_config = ConfigDict(extra="allow")

    # --- Impact ----------------------------------------------------------------------
    impact: float = Field(200.0, description="−Σ_c (w_c ‖f_c‖∞)², f_c in force_unit (kN), worst substep")
    root_acc: float = Field(0.2, description="−‖v̇_root‖², [m/s²]²")
    # --- End-pose tracking (blended in by u(t)) ------------------------------------
    orientation: float = Field(20.0, description="−u(t)‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖², dimensionless")
    joints: float = Field(1.0, description="−u(t)‖q − q̂‖², [rad²]")
    # --- Regularization ----------------------------------------------------------------
    torques: float = Field(1e-3, description="−‖τ‖², [(N·m)²]")
    joint_acc: float = Field(7.5e-7, description="−‖q̈‖², [(rad/s²)²]")
    action_rate: float = Field(0.1, description="−‖a_t − a_{t−1}‖², policy action units")
    action_acc: float = Field(0.05, description="−‖a_t − 2a_{t−1} + a_{t−2}‖², policy action units")
    # --- Positive offset -----------------------------------------------------------
    offset: float = Field(50.0, description="+1")

    # --- settings ------------------------------------------------------------------
    terms: dict[str, str] = Field(
        default_factory=lambda: {name: name for name in BUILTIN_TERMS},
        description="term name -> registered reward function computing it (a name not listed: itself)",
    )
    force_unit: float = Field(1000.0, gt=0, description="[N] per force unit of the impact term: 1000 = kN")
    force_clip: float | None = Field(
        10.0, gt=0, description="clip of each contact-force component [force units] (paper: 10 kN, training only)"
    )
    blend_time: float = Field(2.0, gt=0, description="T_blend [s] of the tracking blend u(t)")

    @model_validator(mode="after")
    def _extra_weights(self) -> "RewardConfig":
        registered = registry.names("fallkit.rewards")
        for key, value in (self.model_extra or {}).items():
            if key not in registered:
                raise ValueError(
                    f"'{key}' is neither a reward setting ({', '.join(_SETTINGS)}) nor a registered reward term "
                    f"({', '.join(registered) or 'none'})"
                )
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"'{key}': a term weight must be a number, got {value!r}")
        negative = {k: w for k, w in self.weights().items() if w < 0}
        if negative:
            name, w = next(iter(negative.items()))
            raise ValueError(
                f"{name}={w:g}: weights must be >= 0 — every term is already signed (penalties return "
                f"negative values), so a negative weight would reward what it should penalise; use {abs(w):g}"
            )
        for term, fn in self.terms.items():
            if fn not in registered:
                raise ValueError(
                    f"terms.{term}: '{fn}' is not a registered reward term ({', '.join(registered) or 'none'})"
                )
        return self

    def weights(self) -> dict[str, float]:
        """Term name -> weight, built-ins first (Table I order), then plugin terms."""
        out = {name: float(getattr(self, name)) for name in BUILTIN_TERMS}
        out.update({k: float(v) for k, v in (self.model_extra or {}).items()})
        return out
