"""One process per GPU: the ``CUDA_VISIBLE_DEVICES`` value of each slot (the drivers that give every run or study
a whole GPU of its own: ``tune_default_repeats --gpus``, ``tune_study --guided-comparison --gpus``)."""
from __future__ import annotations

import os


def gpu_slots(n: int) -> list[str]:
    """The ``CUDA_VISIBLE_DEVICES`` value of each of ``n`` slots: the i-th GPU this process sees (of its own
    ``CUDA_VISIBLE_DEVICES`` list when set, else device ``i``)."""
    visible = [v.strip() for v in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
    return [visible[i] if i < len(visible) else str(i) for i in range(n)] if visible else [str(i) for i in range(n)]
