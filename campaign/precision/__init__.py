"""Precision rounds: a campaign that stops at its error bars. The model of the N_G -> inf row's
errors (``errormodel``), the decisions it leads to (``allocation``) and the planner a run hands
its master (``planner``), which reduces the store with ``campaign.results`` at each decision
point. Imports from ``campaign.plan``, ``campaign.storage`` and ``campaign.results``; the run
(``campaign.run.rounds``) receives the planner and never imports this package."""
