"""Train, evaluate and save an agent chosen by Hydra configs (conf/).

python train.py                                   # CMEPolicyIteration on Pendulum-v1
python train.py env=cartpole agent.gamma=0.99 seed=3
python train.py -m seed=0,1,2                     # a sweep, one run directory per seed
tensorboard --logdir outputs/                     # (multirun/ for sweeps)
"""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from cme_agent.experiment import run


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    """Hydra entry point; returns the evaluation return (for sweepers)."""
    return run(cfg, Path(HydraConfig.get().runtime.output_dir))["eval_mean_reward"]


if __name__ == "__main__":
    main()
