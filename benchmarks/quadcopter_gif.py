"""Write a GIF of a policy flying Quadcopter-v0, drawn by the env's rgb_array renderer.

Usage: ``python -m benchmarks.quadcopter_gif [--model PATH] [--output PATH] [--seed 0] [--overrides KEY=VALUE ...]``.
Without ``--model`` the scripted ``QuadcopterPController`` flies. The env is ``conf/env/quadcopter.yaml``'s
(the one ``python train.py env=quadcopter`` trains on), with the Hydra ``--overrides`` applied
(e.g. ``env.kwargs.process_noise=0.2``).
"""

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from benchmarks.common import command_line, compose_config
from cme_agent.envs.quadcopter import QuadcopterEnv
from cme_agent.envs.quadcopter_controller import QuadcopterPController
from cme_agent.experiment import make_eval_env


def load_policy(model_path: str | None, env: QuadcopterEnv) -> Any:
    """A saved ``CMEPolicyIteration`` model, or the scripted controller when no path is given.

    :param model_path: path of a model saved by ``CMEPolicyIteration.save``, or None.
    :param env: the environment it will fly.
    :return: an object with SB3's ``predict(observation, deterministic=True)``.
    """
    if model_path is None:
        return QuadcopterPController.from_env(env)
    from cme_agent import CMEPolicyIteration

    return CMEPolicyIteration.load(model_path, device="cpu")


def record(env: QuadcopterEnv, policy: Any, seed: int) -> tuple[list[np.ndarray], float, float]:
    """Fly one episode and keep every frame.

    :param env: an env with ``render_mode="rgb_array"``.
    :param policy: an object with SB3's ``predict``.
    :param seed: reset seed.
    :return: frames (uint8, ``(H, W, 3)`` each), the episode return and the final distance
        to the target (m).
    """
    obs, info = env.reset(seed=seed)
    frames, episode_return, done = [env.render()], 0.0, False
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, info = env.step(action)
        frames.append(env.render())
        episode_return += reward
        done = terminated or truncated
    return frames, episode_return, info["distance_to_target"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="saved CMEPolicyIteration model")
    parser.add_argument("--output", default="results/quadcopter_scripted.gif", type=Path)
    parser.add_argument("--seed", type=int, default=0, help="reset seed")
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides of the env config")
    parser.add_argument("--frame-skip", type=int, default=2, help="keep one frame in this many")
    args = parser.parse_args()

    cfg = compose_config(["env=quadcopter", "env.kwargs.render_mode=rgb_array", *args.overrides])
    env = make_eval_env(cfg).unwrapped  # record() resets it with --seed
    frames, episode_return, distance = record(env, load_policy(args.model, env), args.seed)
    images = [Image.fromarray(frame) for frame in frames[:: args.frame_skip]]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    duration_ms = round(1000 * env.agent_dt * args.frame_skip)
    images[0].save(args.output, save_all=True, append_images=images[1:], duration=duration_ms, loop=0)
    print(f"command: `{command_line()}`")
    print(
        f"wrote {args.output} ({len(images)} frames); episode return {episode_return:.2f}, "
        f"final distance to target {distance:.3f} m"
    )


if __name__ == "__main__":
    main()
