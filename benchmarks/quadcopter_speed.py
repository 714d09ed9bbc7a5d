"""Agent steps per second of Quadcopter-v0 in one process, random actions, reset on done.

Usage: ``python -m benchmarks.quadcopter_speed [--steps 5000] [--agent-dt 0.2] [--seed 0]``
"""

import argparse
import shlex
import sys
import time

import numpy as np

from cme_agent.envs.quadcopter import QuadcopterEnv


def measure(env: QuadcopterEnv, steps: int, seed: int) -> float:
    """Agent steps per second over ``steps`` steps of uniformly random actions.

    :param env: the environment.
    :param steps: number of agent steps timed.
    :param seed: seed of the env and of the actions.
    :return: agent steps per second (resets included).
    """
    actions = np.random.default_rng(seed).uniform(-1, 1, (steps, 3)).astype(np.float32)
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000, help="agent steps to time")
    parser.add_argument("--agent-dt", type=float, default=0.2, help="agent step (s); 0.2 as conf/env/quadcopter.yaml")
    parser.add_argument("--process-noise", type=float, default=0.2, help="process noise std")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    env = QuadcopterEnv(agent_dt=args.agent_dt, process_noise=args.process_noise)
    rate = measure(env, args.steps, args.seed)
    print(f"command: python -m benchmarks.quadcopter_speed {shlex.join(sys.argv[1:])}")
    print(f"Quadcopter-v0: {rate:,.0f} agent steps/s ({env.physics_steps} physics steps each)")


if __name__ == "__main__":
    main()
