"""One rank of a DDP run started by a test, as torchrun or a cluster's scheduler starts
ranks: ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT`` set, so that
Lightning joins them instead of launching its own. It runs one `segmo fit` after another
in the same process (the command lines, as a JSON list of argument lists, in argv[1]):
the ranks import torch and Lightning once for all of them.
"""

from __future__ import annotations

import json
import sys

from segmo.training.cli import main

if __name__ == "__main__":
    for args in json.loads(sys.argv[1]):
        main(["fit", *args])
