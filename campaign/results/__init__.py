"""Results: the reducer (``reduce``: its steps in ``reduce_campaign``) with what it reads
(``reading``), its cells (``cells``), scaling fits per size (``scaling``), N_G -> inf row
(``finitesize``) and outputs (``writing``); the fitting maths (``fits``), tables, variant and
system comparisons (``tradeoff``, ``systems``), linear response (``response``), figures
(``plots``, ``draw``), DataFrames (``frames``) and exports (``export``). Imports from
``campaign.plan`` and ``campaign.storage``, never from ``campaign.run``."""
