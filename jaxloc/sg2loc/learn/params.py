"""The learned likelihood parameters (log space) and the loss configuration."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.sg2loc._scores import (
    ObservationConfig,
)

#: The logs of the parameters are clipped to +-LOG_BOUND in :meth:`LikelihoodParams.to_config`.
LOG_BOUND = 15.0

#: The losses of :class:`LossConfig` (``LossConfig.kind``).
LOSS_KINDS = ("nll", "expected_error")
#: The frames the loss is taken at (``LossConfig.frames``): the last one or every one.
LOSS_FRAMES = ("last", "every")


class LikelihoodParams(eqx.Module):
    """The learned likelihood parameters, in log space (float32 scalars, unconstrained).

    Attributes:
        log_sigma: log of ``sigma`` (width of eq. (2)'s Gaussian).
        log_lambda_depth: log of ``lambda_depth``.
        log_lambda_color: log of ``lambda_color``.
    """

    log_sigma: Array
    log_lambda_depth: Array
    log_lambda_color: Array

    @staticmethod
    def from_config(config: ObservationConfig) -> LikelihoodParams:
        """The parameters of an observation config (sigma, lambdas must be positive)."""
        values = {}
        for name in ("sigma", "lambda_depth", "lambda_color"):
            value = float(np.asarray(getattr(config, name)))
            if not (np.isfinite(value) and value > 0):
                raise ValueError(
                    f"config.{name} must be positive and finite to be learned in log space, "
                    f"got {value}"
                )
            values[name] = jnp.asarray(np.log(value), jnp.float32)
        return LikelihoodParams(values["sigma"], values["lambda_depth"], values["lambda_color"])

    def values(self) -> tuple[Array, Array, Array]:
        """``(sigma, lambda_depth, lambda_color)`` float32 scalars (logs clipped to +-LOG_BOUND)."""
        return tuple(
            jnp.exp(jnp.clip(jnp.asarray(v, jnp.float32), -LOG_BOUND, LOG_BOUND))
            for v in (self.log_sigma, self.log_lambda_depth, self.log_lambda_color)
        )

    def to_config(self, base: ObservationConfig) -> ObservationConfig:
        """``base`` with sigma and the lambdas replaced by these parameters (jit-able)."""
        sigma, lambda_depth, lambda_color = self.values()
        return dataclasses.replace(
            base, sigma=sigma, lambda_depth=lambda_depth, lambda_color=lambda_color
        )


class LossConfig(eqx.Module):
    """Which loss and its scales.

    Attributes:
        kind: ``"nll"`` (default) or ``"expected_error"`` (static); see :mod:`jaxloc.sg2loc.learn`.
        frames: ``"last"`` (default): the loss of the posterior after the whole window at its
            last frame; ``"every"``: the mean over k of the loss of the posterior after frames
            1..k at frame k (static; :mod:`jaxloc.sg2loc.learn`, "Per-frame loss").
        position_scale: kernel width / error unit in metres (default 0.1 m).
        yaw_scale: kernel width / error unit in radians (default 5 degrees).
    """

    kind: str = eqx.field(static=True, default="nll")
    frames: str = eqx.field(static=True, default="last")
    position_scale: Array = eqx.field(default=0.1, converter=lambda x: jnp.asarray(x, jnp.float32))
    yaw_scale: Array = eqx.field(
        default=float(np.deg2rad(5.0)), converter=lambda x: jnp.asarray(x, jnp.float32)
    )

    def __check_init__(self):
        if self.kind not in LOSS_KINDS:
            raise ValueError(f"LossConfig.kind must be one of {LOSS_KINDS}, got {self.kind!r}")
        if self.frames not in LOSS_FRAMES:
            raise ValueError(f"LossConfig.frames must be one of {LOSS_FRAMES}, got {self.frames!r}")
