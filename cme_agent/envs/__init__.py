"""Environments of cme_agent, registered with Gymnasium on import.

``Quadcopter-v0``: :class:`cme_agent.envs.quadcopter.QuadcopterEnv`, the paper's
simulated Pelican navigation task. It handles its own time limit (``time_limit``), so it
is registered without ``max_episode_steps``.

``ToyChain-v0``: :class:`cme_agent.envs.toy_chain.ToyChainEnv`, the paper's Toy MDP, a
navigation task on a Markov chain on the interval [-1, 1].
"""

import gymnasium

from cme_agent.envs.quadcopter import QuadcopterEnv, quadcopter_reward, quadcopter_termination
from cme_agent.envs.quadcopter_controller import QuadcopterPController

__all__ = ["QuadcopterEnv", "QuadcopterPController", "quadcopter_reward", "quadcopter_termination"]

if "Quadcopter-v0" not in gymnasium.registry:
    gymnasium.register(id="Quadcopter-v0", entry_point="cme_agent.envs.quadcopter:QuadcopterEnv")
if "ToyChain-v0" not in gymnasium.registry:
    gymnasium.register(id="ToyChain-v0", entry_point="cme_agent.envs.toy_chain:ToyChainEnv")
