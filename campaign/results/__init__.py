"""Results: the reducer, store(s) to a ``Reduction`` of numbers (``reduce``: its steps in
``reduce_campaign``), with what it reads (``finished``), its cells (``cells``), the scaling fits
per size (``scaling``), the N_G -> inf row (``finitesize``), the fitting maths (``fits``), plain
text of values with errors (``tables``), and the optional sections: the variants and systems
compared (``tradeoff``, ``systems``), the jamming point and the protocols compared
(``protocols``), the linear response (``response``). Imports from ``campaign.plan`` and
``campaign.storage``, never from ``campaign.run``; writes no file (``campaign.report`` does)."""
