"""psi's learned metric: one length scale per state dim, fitted on the model's held-out loss."""

from __future__ import annotations

import math

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.config import ModelUpdateConfig
from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.kernel_bank import gaussian_kernel

MAX_LOG_CHANGE = math.log(20.0)
"""A fitted inverse length scale stays within a factor 20 either way of 1 (the box's)."""
RIDGE = 1e-3
"""Ridge of the fit's model, relative to the mean diagonal of its normal equations."""
MIN_HELD_OUT = 200
"""Fewer held-out transitions than this: the fit holds out a second sample of D instead."""


class MetricFitter:
    """Fits ``state_metric``, psi's inverse length scale per state dim (z_s = m * box-normalised s),
    by gradient on the held-out loss of the model, eq. (4), with B refit in closed form.

    The fit's model is a random subset of ``metric_features`` of psi's features, its centres kept
    in place in env units while the metric moves, and B the ridge solution on ``metric_sample``
    transitions of D, differentiable in the metric; its loss is measured on as many held-out
    transitions. ``metric_steps`` Adam steps on log m; the new metric is kept only if it lowers
    that loss. Eq. (5)-(6) are unchanged: the caller refits B on the new psi. The cost is flat in
    |D| (fixed samples) and in q (a fixed subset).

    :param config: the ``model_update`` settings (``metric_*``)
    """

    def __init__(self, config: ModelUpdateConfig) -> None:
        self.config = config

    def due(self, iteration: int) -> bool:
        """Whether this iteration fits the metric: every ``metric_every`` iterations (never at 0)."""
        return self.config.metric_every > 0 and iteration % self.config.metric_every == 0

    def fit(
        self,
        dynamics: CMEDynamics,
        store: TransitionStore,
        holdout: TransitionStore,
        generator: torch.Generator,
        logger: Logger,
    ) -> bool:
        """Fit the metric and set it in ``dynamics`` (:meth:`CMEDynamics.set_state_metric`) if it
        lowers the held-out loss. Logs ``train/metric_loss_before``, ``train/metric_loss_after`` (the
        fit's held-out loss over the targets' variance) and ``train/length_scale_min``/``_max``.

        :return: True when the metric changed (B must be refit)
        """
        if dynamics.q == 0 or len(store) == 0:
            return False
        config = self.config
        train = store.sample(config.metric_sample, generator)
        held = holdout if len(holdout) >= MIN_HELD_OUT else store
        test = held.sample(config.metric_sample, generator)
        columns = torch.randperm(dynamics.q, generator=generator)[: config.metric_features].to(dynamics.weights.device)
        with torch.no_grad():
            inputs = [self._inputs(dynamics, batch, columns) for batch in (train, test)]
        start = dynamics.state_metric.log()
        log_metric = start.clone().requires_grad_(True)
        optimiser = torch.optim.Adam([log_metric], lr=config.metric_lr)
        with torch.enable_grad():
            for _ in range(config.metric_steps):
                optimiser.zero_grad()
                loss = held_out_loss(log_metric, dynamics, columns, *inputs)
                loss.backward()
                optimiser.step()
                with torch.no_grad():
                    log_metric.clamp_(-MAX_LOG_CHANGE, MAX_LOG_CHANGE)
        with torch.no_grad():
            before, after = (float(held_out_loss(m, dynamics, columns, *inputs)) for m in (start, log_metric.detach()))
        logger.record("train/metric_loss_before", before)
        logger.record("train/metric_loss_after", after)
        improved = math.isfinite(after) and after < before
        if improved:
            dynamics.set_state_metric(log_metric.detach().exp())
        scales = 1 / dynamics.state_metric
        logger.record("train/length_scale_min", float(scales.min()))
        logger.record("train/length_scale_max", float(scales.max()))
        return improved

    @staticmethod
    def _inputs(
        dynamics: CMEDynamics, batch: Transitions, columns: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What the loss needs of a batch and does not depend on the metric: the box-normalised
        states (N, obs_dim), the action factor of the chosen features (N, J), and the targets
        phi~(s') (N, p): the successor alone, also with feature dynamics, whose -phi(s) would
        make every state dim look relevant."""
        z_action = dynamics.encode_actions(batch.actions)
        targets = dynamics.phi.successor_targets(batch.next_obs, (~batch.terminated).to(batch.next_obs))
        return dynamics.obs_encoder.normalize(batch.obs), dynamics.psi.action_factor(z_action)[:, columns], targets


def held_out_loss(
    log_metric: torch.Tensor,
    dynamics: CMEDynamics,
    columns: torch.Tensor,
    train: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    test: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """The held-out loss (4) of phi~(s') on the features ``columns`` under the metric exp(log m),
    B fitted by ridge on ``train``, over the variance of ``test``'s targets; differentiable in log m.

    psi_j(s, a) = exp(-a_j ||m * (z_s - c_j)||^2) A_j(a), with z_s and c_j the box-normalised
    state and centre (the bank keeps its centres times the current metric).

    :param log_metric: (obs_dim,) log inverse length scales
    :param columns: (J,) the features used
    :param train: box-normalised states (N, obs_dim), action factor (N, J), targets (N, p)
    :param test: the same for the held-out transitions
    :return: scalar
    """
    metric = log_metric.exp()
    centres = dynamics.psi.centres[columns, : dynamics.psi.state_dim] / dynamics.state_metric * metric
    inv_two_sq_bandwidth = dynamics.psi.inv_two_sq_bandwidth[columns]
    (z_train, action_train, y_train), (z_test, action_test, y_test) = train, test
    psi_train = gaussian_kernel(z_train * metric, centres, inv_two_sq_bandwidth) * action_train
    psi_test = gaussian_kernel(z_test * metric, centres, inv_two_sq_bandwidth) * action_test
    gram = psi_train.T.double() @ psi_train.double()
    ridge = RIDGE * gram.diagonal().mean() + 1e-9
    weights = torch.linalg.solve(
        gram + ridge * torch.eye(len(gram), dtype=gram.dtype), psi_train.T.double() @ y_train.double()
    )
    residual = y_test.double() - psi_test.double() @ weights
    return residual.square().sum(1).mean() / (y_test.double() - y_test.double().mean(0)).square().sum(1).mean()
