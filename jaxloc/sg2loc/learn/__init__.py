"""Learning the SG2Loc likelihood parameters (sigma, lambda_depth, lambda_color) by gradient.

Parameters. :class:`LikelihoodParams` holds ``log sigma``, ``log lambda_depth`` and
``log lambda_color`` (unconstrained floats; the values are their exponentials, so they stay
positive). :meth:`LikelihoodParams.to_config` maps them into an
:class:`~jaxloc.sg2loc.ObservationConfig`, clipping the logs to ``[-LOG_BOUND, LOG_BOUND]``
so that eq. (2) stays finite in float32 (``(S_max - S)^2 / (2 sigma^2)`` cannot overflow). The
motion noise (``sigma_trans``, ``sigma_rot``) is not learned: the loss below holds the particles
fixed, so it does not depend on the motion noise (see "Why not through resampling").

Loss. One training sample is a *window* of ``K`` consecutive frames of a synthetic episode and a
fixed set of ``N`` particles (:func:`window_particles`): half drawn uniformly in a box around the
true pose of the window's first frame (``LOCAL_HALF_WIDTH`` 0.4 m, ``LOCAL_YAW_HALF_RANGE`` 20 deg),
half uniformly over the room's floor at camera heights (round 0's spread). The particles are carried
through the window by the measured (noisy) ego-motion without noise, which is the filter's
prediction step with the noise switched off. Their weights after the window are the product of the
``K`` frames' likelihoods, i.e. ``log w = log_softmax(sum_k log L_k)`` with ``log L_k`` eq. (2) of
the scores the filter computes (:func:`jaxloc.sg2loc._scores.particle_log_likelihood` on the
particles' rendered views). That is the filter's posterior over this particle set: sequential
importance sampling without resampling. The default loss (``"nll"``) is the negative log density of
the true last-frame pose under the weighted particle mixture with a Gaussian kernel of
``position_scale`` metres and ``yaw_scale`` radians::

    loss = -log sum_i w_i exp(-(e_pos_i / position_scale)^2 / 2 - (e_yaw_i / yaw_scale)^2 / 2)

The defaults (kernel 0.1 m / 5 deg, local box +-0.4 m / +-20 deg, the whole window's posterior)
were chosen by measurement on held-out scenes against the filter's hand-set parameters: a
0.25 m / 10 deg kernel with the fine round's box (+-0.8 m / +-45 deg), the per-frame loss and the
filter windows below all did worse than these (``experiments/results/learn/NOTE.md``).

Per-frame loss (``LossConfig(frames="every")``). The filter resamples after every frame, so it acts
on the posterior after frames 1..k for every k, not only on the one after the whole window; a
likelihood that is confident on a wrong mode after the first frame collapses the particle set there
even when the window as a whole points to the truth. With ``frames="every"`` the loss is the mean
over k = 1..K of the loss of the posterior after frames 1..k (``log w_k = log_softmax(sum_{j<=k}
log L_j)``) at frame k's true pose, so that over-confidence is paid for. Measured, it does the
opposite: the learned likelihood gets sharper (lambda_depth 12.3 vs 5.7 with the default loss) and
the filter's R@(0.25 m, 10 deg) on 50 held-out scenes drops from 0.72 (hand-set) to 0.51; it is
kept for comparison.

Filter windows (:func:`filter_windows`). The windows above draw half of their particles close to the
truth, far denser there than the filter's early rounds, which spread a few hundred particles over
the whole room; a sharp likelihood is rewarded on such sets and punished by the filter. One-frame
windows of the particles a filter run actually weighted (every round and frame of
:func:`jaxloc.sg2loc.localize`) have the filter's own density: the loss of such a window is the
loss of the filter's update at that frame. The particle sets depend on the parameters that ran the
filter, so training alternates runs and fits (``experiments/learn_params.py --windows filter``).
Measured on 50 held-out scenes, the parameters learned this way beat the hand-set ones on the
median errors and recalls over all frames but not on the last frame, and are no better than those
learned on the default windows.

A proper scoring rule: it rewards weight near the truth and punishes confident weight on a wrong
mode, which is what the filter needs (an over-confident likelihood collapses the particle set onto
a wrong mode at resampling, an under-confident one never concentrates). The alternative
``"expected_error"`` is the weighted mean of ``e_pos / position_scale + e_yaw / yaw_scale``; it is
minimised by putting all weight on the best-scoring particle, so it tends to drive sigma to zero
(over-confidence), and is offered for comparison.

The renders and the scores ``s``, ``s_d``, ``s_i`` do not depend on the parameters, only their
combination in eq. (2) does; they are computed once per window (:func:`score_window`, jitted) and
the training loop differentiates eq. (2) and the loss on the stored scores. The gradient is the
same as differentiating through rendering and scoring (whose derivative with respect to the
parameters is zero).

Why not through resampling. Resampling draws discrete ancestor indices: its output is piecewise
constant in the weights, so its derivative is zero almost everywhere and the true gradient of the
filter's estimate is carried by the jumps. Differentiable relaxations (soft resampling, optimal
transport resampling) are biased, much costlier, and would make the gradient depend on the
particle noise of a whole sequence. Between two resamplings, however, the filter's posterior over
a fixed particle set is exactly the product of the likelihoods above, so holding the set fixed
differentiates the part of the filter that the parameters control, without these problems.
"""

from jaxloc._lazy import public_names
from jaxloc.sg2loc.learn.losses import (
    batch_loss as batch_loss,
    config_log_likelihood as config_log_likelihood,
    expected_position_error as expected_position_error,
    prefix_log_weights as prefix_log_weights,
    window_log_weights as window_log_weights,
    window_loss as window_loss,
)
from jaxloc.sg2loc.learn.params import (
    LOG_BOUND as LOG_BOUND,
    LOSS_FRAMES as LOSS_FRAMES,
    LOSS_KINDS as LOSS_KINDS,
    LikelihoodParams as LikelihoodParams,
    LossConfig as LossConfig,
)
from jaxloc.sg2loc.learn.training import (
    History as History,
    TrainState as TrainState,
    adam as adam,
    make_train_step as make_train_step,
    train as train,
)
from jaxloc.sg2loc.learn.windows import (
    LOCAL_HALF_WIDTH as LOCAL_HALF_WIDTH,
    LOCAL_YAW_HALF_RANGE as LOCAL_YAW_HALF_RANGE,
    Windows as Windows,
    concat_windows as concat_windows,
    filter_windows as filter_windows,
    score_particle_set as score_particle_set,
    score_particles as score_particles,
    score_window as score_window,
    sequence_windows as sequence_windows,
    window_particles as window_particles,
)

__all__ = public_names(__file__)
