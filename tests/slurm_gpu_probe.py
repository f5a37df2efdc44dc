"""The task function of the GPU jobs in tests/run/test_slurm_cluster.py: the synthetic task, whose
warm-up also records, per process, what that process was given and chose.

Each warm-up (the master's; the node's, by the first rank of every other node; every worker's
before its first task) appends a line to ``HOST-PID.jsonl`` in ``$CAMPAIGN_TEST_GPU_PROBE``: the
process's MPI rank and rank on the node, the GPUs SLURM gave its step (``SLURM_STEP_GPUS``),
``CUDA_VISIBLE_DEVICES`` as it is then (a worker has set it to its own GPU before its first
warm-up), the worker's GPU index (``gpu_device``; "none" on the master) and the ``device: gpu``
protocols it was asked to warm up.
"""

from __future__ import annotations

import json
import os
import socket

from campaign.run.worker import SyntheticTask


class ProbeTask(SyntheticTask):
    def warm_up(self, context) -> None:
        directory = os.environ.get("CAMPAIGN_TEST_GPU_PROBE")
        if not directory:
            return
        env = os.environ
        record = {"host": socket.gethostname(), "pid": os.getpid(), "rank": env.get("PMI_RANK"),
                  "local": env.get("MPI_LOCALRANKID") or env.get("SLURM_LOCALID"),
                  "slurm_gpus": env.get("SLURM_STEP_GPUS"), "visible": env.get("CUDA_VISIBLE_DEVICES"),
                  "gpu_device": context.get("gpu_device", "none"),
                  "gpu_warm_ups": [p for p in context.get("protocol_warmups") or [] if p.get("device") == "gpu"]}
        with open(os.path.join(directory, f"{record['host']}-{record['pid']}.jsonl"), "a") as fh:
            fh.write(json.dumps(record) + "\n")
