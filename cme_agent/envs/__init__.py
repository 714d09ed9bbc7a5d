"""Environments of cme_agent, registered with Gymnasium on import.

``Quadcopter-v0``: :class:`cme_agent.envs.quadcopter.QuadcopterEnv`, the paper's
simulated Pelican navigation task. It handles its own time limit (``time_limit``), so it
is registered without ``max_episode_steps``.

``ToyChain-v0``: :class:`cme_agent.envs.toy_chain.ToyChainEnv`, the paper's Toy MDP, a
navigation task on a Markov chain on the interval [-1, 1].

``PointGoal2D-v0``: :class:`cme_agent.envs.point_goal.PointGoal2D`, a damped 2-D point mass
that must reach a goal only the env knows (the agent learns the reward). The env never ends an
episode itself, so it is registered with ``max_episode_steps=100``.
"""

import gymnasium

from cme_agent.envs.quadcopter import QuadcopterEnv, quadcopter_reward, quadcopter_termination
from cme_agent.envs.quadcopter_controller import QuadcopterPController

__all__ = ["QuadcopterEnv", "QuadcopterPController", "quadcopter_reward", "quadcopter_termination"]

if "Quadcopter-v0" not in gymnasium.registry:
    gymnasium.register(id="Quadcopter-v0", entry_point="cme_agent.envs.quadcopter:QuadcopterEnv")
if "ToyChain-v0" not in gymnasium.registry:
    gymnasium.register(id="ToyChain-v0", entry_point="cme_agent.envs.toy_chain:ToyChainEnv")
if "PointGoal2D-v0" not in gymnasium.registry:
    gymnasium.register(id="PointGoal2D-v0", entry_point="cme_agent.envs.point_goal:PointGoal2D", max_episode_steps=100)
