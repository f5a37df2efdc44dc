"""What ``campaign verify`` checks in a store written before the block checksums (0.2.7 and older),
where nothing records which rows a block held (docs/STORE.md, "Stores written before the block
checksums"): each block of the task table's identities against the spec's tasks of its rows, in
their order (``identities``, the spec's, also name a damaged id block's tasks in any store), and
each finished task the journal still holds against its row in the store. Called by
``campaign.storage.integrity.Scan`` (``scan``: the scan, whose ``add`` records what is damaged).
"""

from __future__ import annotations

import numpy as np

from campaign.storage.checksums import PROTECTION_ATTR, _text, good_scalar_name
from campaign.storage.damage import Damage


def identities(spec) -> dict:
    """The task table's identity columns (id, variant, N, E, seed) as the spec gives them, stored types."""
    from campaign.plan.tasks import expand
    from campaign.storage.layout import VARIANT_LEN, fixed

    tasks = expand(spec)
    return {"id": np.array([t.id.encode() for t in tasks], "S32"),
            "variant": np.array([fixed(t.variant, VARIANT_LEN) for t in tasks], f"S{VARIANT_LEN}"),
            "N": np.array([t.N for t in tasks], np.int64), "E": np.array([t.E for t in tasks], np.float64),
            "seed": np.array([t.seed for t in tasks], np.int64)}


def expected_identities(scan):
    """``identities`` of the scanned store's spec when the store has no block checksums (what its
    task table is checked against, ``identity_blocks``), else None; and the report's ``unprotected``
    and ``protection`` (the store's ``block_checksums`` attribute: how it came to have them)."""
    r = scan.report
    r.unprotected = not scan.summed
    try:
        r.protection = _text(scan.f.attrs.get(PROTECTION_ATTR)) or ""
    except Exception:  # noqa: BLE001 - unreadable root attributes: reported by the scan
        r.protection = ""
    return identities(r.spec) if not scan.summed and r.spec is not None and r.spec.n_tasks == r.T else None


def identity_blocks(scan, col, lo, data):
    """Whether each block of rows ``data`` (from row ``lo``) of the identity column ``col`` was read from
    its own place: its values, in their rows' order, are those the spec gives its rows
    (``scan.expected``, from ``expected_identities``; nothing to check without)."""
    if scan.expected is None or col not in scan.expected:
        return
    want, B = scan.expected[col], max(1, scan.report.B)
    data = np.asarray(data)
    for a in range(lo, lo + len(data), B):
        b = min(a + B, lo + len(data))
        if not np.array_equal(data[a - lo:b - lo], want[a:b]):
            scan.add(Damage(f"tasks/{col}", f"rows {a}-{b - 1} are not the spec's {col} of those rows, in their "
                            "order: the block was read from another place (its chunk index is damaged)",
                            span=(a, b), repair="rewrite",
                            note="the task identities it held are rewritten from the spec"))


def journal_rows(scan):
    """Every finished task the journal has a record of (a run killed before its checkpoint) against the
    row the store holds for it, where both say done. A row that differs was read from another place, or
    changed since it was written: a repair drops it, and the next run replays the record."""
    from campaign.storage.journal import scan_journal
    from campaign.storage.layout import DONE, row_values

    r = scan.report
    if scan.summed:  # the block checksums say it all
        return
    try:
        with open(str(scan.path) + ".journal", "rb") as fh:
            records, _, _ = scan_journal(fh.read())
    except OSError:
        return
    head = records[0][0] if records else {}
    if r.spec is None or r.status is None or head.get("type") != "header" or head.get("spec_hash") != r.spec.hash:
        return
    last = {int(m["index"]): (m, a) for m, a in records[1:] if m.get("type") == "task" and "index" in m}
    rows = sorted(i for i, (m, _) in last.items() if 0 <= i < r.T and r.status[i] == DONE
                  and int(m.get("status", -1)) == DONE)
    if not rows:
        return
    try:
        names = ["tasks/attempts"] + [f"scalars/{n}" for n in scan.f["scalars"].keys() if good_scalar_name(n)]
    except Exception:  # noqa: BLE001 - reported with the block datasets
        return
    names += [f"histograms/{h}/counts" for h in r.edges]
    B = max(1, r.B)
    lost = {d.span for d in r.damage if d.span is not None}
    for name in names:
        bad = []
        for block in sorted({i // B for i in rows}):
            a, b = block * B, min(block * B + B, r.T)
            if any(lo < b and a < hi for lo, hi in lost):
                continue  # its rows are dropped already
            try:
                data = scan.f[name][a:b]
            except Exception:  # noqa: BLE001 - reported with the block datasets
                continue
            for i in (i for i in rows if a <= i < b):
                want = row_values(*last[i], r.edges, [name])[name]
                got = data[i - a]
                same = (np.array_equal(got, want) if name.startswith("histograms/") else
                        got == want or (name.startswith("scalars/") and np.isnan(got) and np.isnan(want)))
                if not same:
                    bad.append(i)
        if bad:
            scan.add(Damage(name, f"differs from the journal's record of the task at {len(bad)} row(s): read from "
                                  "another place, or changed since it was written", rows=np.asarray(bad, np.int64),
                            note="dropped; the next run replays the journal's record"))
