"""Writes tests/data/v027-plain.h5 and v027-configs.h5 (with their journals): stores as jamming-campaign
0.2.7 wrote them, before the block checksums (tests/storage/test_unprotected.py). Run it with 0.2.7's code:

    git worktree add --detach /tmp/v027 cd07d52          # the commit of 0.2.7
    PYTHONPATH=/tmp/v027 python tests/data/v027_stores.py

Synthetic tasks (no kernels), blocks of 4 rows (so that a small store has many chunks), the specs of
tests/storage/test_reader_damage.py; the second keeps configurations and has failed tasks (every task of seed 1).
The specs are written out here on purpose, not imported from the tests: this script runs on 0.2.7's
tree, and the stores it wrote are frozen whatever the tests' specs become.
"""

import os
import sys
from pathlib import Path

import campaign
import campaign.storage.store
from campaign import cli

SPECS = {
    "plain": """\
name: dmg
seed: 21
grid: {N_G: [16, 24, 32], E_G: [1.0e-3, 1.0e-5], seeds: 6}
observables: [scalars, connectivity]
bins: {z_g: {range: [-0.5, 12.5], count: 13}, z_v: {range: [2.5, 12.5], count: 10}}
""",
    "configs": """\
name: integ
seed: 5
grid: {N_G: [16, 24], E_G: [1.0e-3, 1.0e-5], seeds: 3}
variants: [{name: lad, start: ladder}]
observables: [scalars, connectivity, void_areas]
bins: {z_g: {range: [-0.5, 12.5], count: 13}, z_v: {range: [2.5, 12.5], count: 10}, alpha_v: {range: [0, 2], count: 40}}
store: {configurations: true}
run: {retries: 0}
""",
}

if __name__ == "__main__":
    assert campaign.__version__ == "0.2.7", f"run with 0.2.7's code on PYTHONPATH, not {campaign.__version__}"
    here = Path(__file__).resolve().parent
    campaign.storage.store.BLOCK_ROWS = 4
    for name, text in SPECS.items():
        spec, out = here / f"v027-{name}.yaml", here / f"v027-{name}.h5"
        spec.write_text(text)
        for p in here.glob(out.name + "*"):
            p.unlink()
        os.environ["CAMPAIGN_SYNTHETIC_FAIL"] = "seed:1" if name == "configs" else "none"
        code = cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--task-function", "synthetic",
                         "--quiet"])
        spec.unlink()
        Path(str(out) + ".progress.json").unlink(missing_ok=True)
        if code != 0:
            sys.exit(code)
