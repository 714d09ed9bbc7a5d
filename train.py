"""Train, evaluate and save an agent chosen by Hydra configs (conf/).

python train.py                                   # CMEPolicyIteration on Pendulum-v1
python train.py env=cartpole agent.gamma=0.99 seed=3
python train.py -m seed=0,1,2                     # a sweep, one run directory per seed
python train.py resume=outputs/.../checkpoint.zip # continue an interrupted run in its directory
tensorboard --logdir outputs/                     # (multirun/ for sweeps)
"""

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from cme_agent.experiment import resume_run_dir, run

OmegaConf.register_new_resolver("cme_run_dir", resume_run_dir, replace=True)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    """Hydra entry point; returns the final evaluation return (the objective of sweepers)."""
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    return run(cfg, run_dir, hydra_cfg.overrides.task, sys.argv[0], hydra_cfg.runtime.choices)["eval_mean_reward"]


if __name__ == "__main__":
    main()
