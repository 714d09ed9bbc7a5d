"""The SB3 logger of a run directory, which a resumed run continues rather than restarts, and
what it prints.

At ``verbose=1`` stdout gets SB3's table every ``log_interval`` iterations and one line per
evaluation, beside the progress bar; ``progress.csv`` and TensorBoard get every iteration.

A run resumed from a checkpoint taken at step T writes into the same folder: ``progress.csv``
keeps its rows up to step T and goes on from there, and the TensorBoard events of the
interrupted run after step T (which the resumed run redoes) are purged (``SummaryWriter``'s
``purge_step``), so TensorBoard shows one run with one curve.
"""

from __future__ import annotations

import csv
import pathlib
import sys
from collections.abc import Sequence
from typing import Any

from stable_baselines3.common.logger import CSVOutputFormat, HumanOutputFormat, KVWriter, Logger, TensorBoardOutputFormat
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

STEP_KEY = "time/total_timesteps"  # the step column of progress.csv
EVAL_KEY = "eval/mean_reward"  # the key of an evaluation's dump (cme_agent.callbacks.PeriodicEvaluation)


class SummaryOutputFormat(HumanOutputFormat):
    """SB3's stdout table, of every ``every``-th dump of training only, and each evaluation as one line
    (``evaluation at 2000 steps: -143.2 +- 27.2, episodes of 200.0 steps``).

    Lines go through ``tqdm.write``, so that they appear above a progress bar rather than through it.

    :param every: dumps (iterations, for CMEPolicyIteration) between tables; 0: no table
    """

    def __init__(self, every: int) -> None:
        super().__init__(sys.stdout)
        self.every = every
        self._dumps = 0

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        if EVAL_KEY in key_values:
            self._emit(
                f"evaluation at {step} steps: {key_values[EVAL_KEY]:.1f} +- {key_values['eval/std_reward']:.1f}, "
                f"episodes of {key_values['eval/mean_ep_length']:.1f} steps"
            )
            return
        self._dumps += 1
        if self.every and self._dumps % self.every == 0:
            super().write(key_values, key_excluded, step)  # SB3's table, written through tqdm.write

    def write_sequence(self, sequence: Sequence[Any]) -> None:
        self._emit(" ".join(map(str, sequence)))

    def _emit(self, line: str) -> None:
        tqdm.write(line, file=sys.stdout)  # sys.stdout as it is now: a progress bar's, while one is shown
        sys.stdout.flush()


class ResumedTensorBoardFormat(TensorBoardOutputFormat):
    """SB3's TensorBoard output continuing the events in ``folder``: those of steps >= ``purge_step``
    are hidden from TensorBoard (they are rewritten by the resumed run).

    :param folder: the TensorBoard log folder of the interrupted run
    :param purge_step: the first step the resumed run logs again
    """

    def __init__(self, folder: str, purge_step: int) -> None:  # not super().__init__: it makes a writer without purge_step
        self.writer = SummaryWriter(log_dir=folder, purge_step=purge_step)
        self._is_closed = False


def resumed_csv(path: pathlib.Path, last_step: int) -> CSVOutputFormat:
    """SB3's CSV output over ``path`` keeping its rows of steps <= ``last_step`` (by ``time/total_timesteps``).

    :param path: the ``progress.csv`` of the interrupted run (it need not exist)
    :param last_step: the step of the checkpoint the run resumes from
    """
    rows: list[dict[str, str]] = []
    keys: list[str] = []
    if path.exists():
        with path.open(newline="") as file:
            reader = csv.DictReader(file)
            keys = list(reader.fieldnames or [])
            rows = [row for row in reader if row.get(STEP_KEY) and float(row[STEP_KEY]) <= last_step]
    output = CSVOutputFormat(str(path))
    if keys:
        writer = csv.DictWriter(output.file, fieldnames=keys, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        output.file.flush()
        output.keys = keys
    return output


def configure_run_logger(run_dir: pathlib.Path, verbose: int, resumed_at: int | None = None, log_interval: int = 1) -> Logger:
    """The logger of ``train.py``: stdout (``verbose``), ``progress.csv`` and TensorBoard events in
    ``run_dir``, continuing those of an interrupted run when ``resumed_at``.

    :param run_dir: the run directory
    :param verbose: 0 nothing on stdout; 1 SB3's table every ``log_interval`` iterations and one
        line per evaluation (:class:`SummaryOutputFormat`); 2 every table, evaluations' too
    :param resumed_at: the step of the checkpoint the run resumes from (None: a new run)
    :param log_interval: iterations between the tables printed at ``verbose=1`` (0: none)
    :return: a logger for ``model.set_logger``
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    formats: list[KVWriter] = []
    if verbose == 1:
        formats.append(SummaryOutputFormat(log_interval))
    elif verbose >= 2:
        formats.append(HumanOutputFormat(sys.stdout))
    if resumed_at is None:
        formats += [CSVOutputFormat(str(run_dir / "progress.csv")), TensorBoardOutputFormat(str(run_dir))]
    else:
        formats += [resumed_csv(run_dir / "progress.csv", resumed_at), ResumedTensorBoardFormat(str(run_dir), resumed_at + 1)]
    return Logger(folder=str(run_dir), output_formats=formats)
