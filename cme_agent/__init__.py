"""cme_agent: model-based RL with online conditional mean embeddings and greedy feature selection
(Lever, Stafford & Shawe-Taylor, 2014), with the stable-baselines3 interface."""

from cme_agent import envs  # noqa: F401  (registers Quadcopter-v0)
from cme_agent.algorithm import CMEPolicyIteration
from cme_agent.kernel_baseline import KernelPolicyIteration
from cme_agent.policy import CMEPolicy
from cme_agent.rewards import KNOWN_REWARDS, RewardSpec, register_reward

__all__ = ["KNOWN_REWARDS", "CMEPolicy", "CMEPolicyIteration", "KernelPolicyIteration", "RewardSpec", "register_reward"]
__version__ = "0.1.0"
