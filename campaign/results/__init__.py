"""Results: the reducer, store(s) to a ``Reduction`` of numbers (``reduce``: its steps in
``reduce_campaign``, and ``SECTIONS``, the registry of its optional sections), with what it reads
(``finished``), its cells (``cells``), the scaling fits per size (``scaling``), the N_G -> inf row
(``finitesize``), the fitting maths (``fits``), every bootstrap and its generator
(``bootstrap``), plain text of values with errors (``tables``), and the sections, each declaring
what it computes and adds to every output (``sections``): the variants and systems compared
(``tradeoff``, ``systems``), the linear response (``response``), the jamming point and the
protocols compared (``protocols``). Imports from ``campaign.plan`` and ``campaign.storage``,
never from ``campaign.run``, ``campaign.precision`` or ``campaign.report``; writes no file
(``campaign.report`` does)."""
