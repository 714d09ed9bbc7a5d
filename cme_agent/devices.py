"""Where reading a device value on the host costs nothing."""

from __future__ import annotations

import torch


def host_reads_are_free(device: torch.device) -> bool:
    """Whether reading a tensor's value on the host (``float(t)``, ``bool(t)``) is free on ``device``:
    on the CPU it is, on a GPU it is a host synchronisation that the inner loops avoid (they then
    keep the value on the device: a step size as a 0-dim tensor, a stopping rule as a flag).

    :param device: where the tensors live
    """
    return device.type == "cpu"
