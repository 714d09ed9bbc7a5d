"""The SB3 logger of a run directory, which a resumed run continues rather than restarts.

A run resumed from a checkpoint taken at step T writes into the same folder: ``progress.csv``
keeps its rows up to step T and goes on from there, and the TensorBoard events of the
interrupted run after step T (which the resumed run redoes) are purged (``SummaryWriter``'s
``purge_step``), so TensorBoard shows one run with one curve.
"""

from __future__ import annotations

import csv
import pathlib
import sys

from stable_baselines3.common.logger import CSVOutputFormat, HumanOutputFormat, KVWriter, Logger, TensorBoardOutputFormat
from torch.utils.tensorboard import SummaryWriter

STEP_KEY = "time/total_timesteps"  # the step column of progress.csv


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


def configure_run_logger(run_dir: pathlib.Path, verbose: int, resumed_at: int | None = None) -> Logger:
    """The logger of ``train.py``: SB3's log table on stdout (``verbose``), ``progress.csv`` and
    TensorBoard events in ``run_dir``, continuing those of an interrupted run when ``resumed_at``.

    :param run_dir: the run directory
    :param verbose: 1 to print SB3's log tables
    :param resumed_at: the step of the checkpoint the run resumes from (None: a new run)
    :return: a logger for ``model.set_logger``
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    formats: list[KVWriter] = [HumanOutputFormat(sys.stdout)] if verbose else []
    if resumed_at is None:
        formats += [CSVOutputFormat(str(run_dir / "progress.csv")), TensorBoardOutputFormat(str(run_dir))]
    else:
        formats += [resumed_csv(run_dir / "progress.csv", resumed_at), ResumedTensorBoardFormat(str(run_dir), resumed_at + 1)]
    return Logger(folder=str(run_dir), output_formats=formats)
