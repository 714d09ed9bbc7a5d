"""CMEPolicy: the greedy policy of the smoothed Q function (paper section 2.2, DESIGN.md fact 2).

``Q_k(s, a) = r(s, a) + <theta_phi, phi(s)> + <theta_psi, psi(s, a)>``, where r is the known
step reward and the weights accumulate gamma <w, B psi>, the expected terminal bonus and a
learned reward. Acting greedily costs O(q) per candidate action, whatever the iteration.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from cme_agent.config import ActionSearchConfig, ObservationConfig, StateFeatureConfig, build_config
from cme_agent.encoding import ActionEncoder, ObservationEncoder
from cme_agent.kernel_bank import KernelBank
from cme_agent.rewards import RewardSpec
from cme_agent.state_features import make_state_features


def _zero_reward(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return torch.zeros(obs.shape[0], dtype=obs.dtype, device=obs.device)


class CMEPolicy(BasePolicy):
    """Greedy policy over candidate actions of the smoothed Q function.

    :param observation_space: a 1-D ``Box``
    :param action_space: a 1-D ``Box`` or a ``Discrete``
    :param lr_schedule: unused (SB3 signature); the model's step size lives in the algorithm
    :param phi: the state feature map: a :class:`StateFeatureConfig` or its dict, or a user
        map (``nn.Module`` or callable) from obs (N, obs_dim) to (N, p0)
    :param observation: normalisation bounds and angle pairs (:class:`ObservationConfig` or dict)
    :param action_search: greedy search over Box actions (:class:`ActionSearchConfig` or dict)
    :param n_features: initial size q of the kernel bank psi (the saved size when loading)
    :param candidate_seed: seed of the sampled action candidates (Box actions, high dims)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Callable[[float], float] | None = None,
        phi: StateFeatureConfig | dict[str, Any] | nn.Module | Callable[[torch.Tensor], torch.Tensor] | None = None,
        observation: ObservationConfig | dict[str, Any] | None = None,
        action_search: ActionSearchConfig | dict[str, Any] | None = None,
        n_features: int = 0,
        candidate_seed: int = 0,
    ) -> None:
        super().__init__(observation_space, action_space, squash_output=False)
        self.phi_spec = phi
        self.observation_config = build_config(ObservationConfig, observation, "observation")
        self.action_search = build_config(ActionSearchConfig, action_search, "action_search")
        self.candidate_seed = candidate_seed
        phi_config = phi if callable(phi) else build_config(StateFeatureConfig, phi, "phi")
        self.obs_encoder = ObservationEncoder(observation_space, self.observation_config)
        self.action_encoder = ActionEncoder(action_space)
        self.phi = make_state_features(phi_config, self.obs_encoder)
        self.psi = KernelBank(self.obs_encoder.dim, self.action_encoder.dim, n_features)
        self.register_buffer("theta_phi", torch.zeros(self.phi.width))
        self.register_buffer("theta_psi", torch.zeros(n_features))
        self.register_buffer("candidates", self._make_candidates())
        self.reward_spec = RewardSpec(_zero_reward)

    def _make_candidates(self) -> torch.Tensor:
        """Candidate actions in env units: all Discrete actions (K,), or a Box grid / sample (K, act_dim)."""
        if self.action_encoder.discrete:
            return torch.arange(self.action_encoder.n_actions)
        dims = self.action_encoder.dim
        search = self.action_search
        if dims <= search.max_grid_dims:
            axis = torch.linspace(-1, 1, search.grid_size)
            encoded = torch.tensor(list(itertools.product(axis.tolist(), repeat=dims)), dtype=torch.float32)
        else:
            generator = torch.Generator().manual_seed(self.candidate_seed)
            sampled = torch.rand(search.n_samples, dims, generator=generator) * 2 - 1
            encoded = torch.cat([torch.zeros(1, dims), sampled])
        return self.action_encoder.decode(encoded)

    @property
    def device(self) -> torch.device:
        """The device of the policy's tensors (it has buffers, no parameters)."""
        return self.theta_phi.device

    @property
    def n_features(self) -> int:
        """q, the current size of the kernel bank psi."""
        return self.psi.n_features

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            phi=self.phi_spec,
            observation=self.observation_config,
            action_search=self.action_search,
            n_features=self.n_features,
            candidate_seed=self.candidate_seed,
        )
        return data

    def state_action_features(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """psi(s, a) at paired states and actions: (N, obs_dim), (N, ...) -> (N, q)."""
        return self.psi(self.obs_encoder.normalize(obs), self.action_encoder.encode(actions))

    def step_reward(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The known per-step reward r(s, a): (N, obs_dim), (N, ...) -> (N,)."""
        return self.reward_spec.step_reward(obs, actions)

    def q_values(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Q_k at paired states and actions: (N, obs_dim), (N, ...) -> (N,)."""
        return (
            self.step_reward(obs, actions)
            + self.phi(obs) @ self.theta_phi
            + self.state_action_features(obs, actions) @ self.theta_psi
        )

    def candidate_q_values(self, obs: torch.Tensor) -> torch.Tensor:
        """Q_k at every candidate action: (N, obs_dim) -> (N, K), one (N, q) x (q, K) product."""
        n, k = obs.shape[0], self.candidates.shape[0]
        state_part, action_part = self.psi.factors(
            self.obs_encoder.normalize(obs), self.action_encoder.encode(self.candidates)
        )
        kernel_term = (state_part * self.theta_psi) @ action_part.T
        pairs_obs = obs.repeat_interleave(k, dim=0)
        pairs_actions = self.candidates.repeat(n, *([1] * (self.candidates.ndim - 1)))
        rewards = self.step_reward(pairs_obs, pairs_actions).reshape(n, k)
        return rewards + kernel_term + (self.phi(obs) @ self.theta_phi).unsqueeze(1)

    def greedy(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pi_{k+1} = greedy(Q_k): the best candidate, refined by gradient ascent if configured.

        :param obs: (N, obs_dim) observations
        :return: actions (N, act_dim) in env units or (N,) indices, and their Q values (N,)
        """
        values, best = self.candidate_q_values(obs).max(dim=1)
        actions = self.candidates[best]
        if self.action_encoder.discrete or self.action_search.refine_steps == 0:
            return actions, values
        return self._refine(obs, actions, values)

    def _refine(self, obs: torch.Tensor, actions: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Projected normalised-gradient ascent on Q through psi, from the best candidate;
        a refined action replaces the candidate only where it has a higher Q."""
        encoded = self.action_encoder.encode(actions).detach().requires_grad_(True)
        with torch.enable_grad():
            for _ in range(self.action_search.refine_steps):
                q = self.q_values(obs, self.action_encoder.decode(encoded))
                (grad,) = torch.autograd.grad(q.sum(), encoded)
                with torch.no_grad():
                    encoded += self.action_search.refine_lr * grad / grad.norm(dim=1, keepdim=True).clamp_min(1e-12)
                    encoded.clamp_(-1, 1)
        refined = self.action_encoder.decode(encoded.detach())
        refined_values = self.q_values(obs, refined)
        better = refined_values > values
        return torch.where(better.unsqueeze(1), refined, actions), torch.where(better, refined_values, values)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> torch.Tensor:
        """The greedy action (the policy is deterministic; exploration belongs to learn())."""
        assert isinstance(observation, torch.Tensor)
        return self.greedy(observation.float())[0]

    def grow(self, centres: torch.Tensor, bandwidths: torch.Tensor) -> None:
        """Append features to psi and zero weights to theta_psi (the zero-padding of fact 2).

        :param centres: (l, state_dim + action_dim) normalised centres
        :param bandwidths: (l,) bandwidths
        """
        self.psi.append(centres, bandwidths)
        self.theta_psi = torch.nn.functional.pad(self.theta_psi, (0, bandwidths.shape[0]))
