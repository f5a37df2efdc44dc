"""What people read, made from a ``Reduction`` (``campaign.results``) or a store: the tables,
CSVs, JSON and ``/reduced`` group written (``writing``), the figures (``plots``: the paper's and
``make_figures``; ``sectionplots``: the sections'; ``plotkit``: what they share), pictures of one
packing (``draw``), DataFrames (``frames``) and exports to other programs' formats (``export``).
Imports from every wing below it but ``campaign.precision``; nothing but the commands imports it."""
