"""The plan: a campaign spec parsed and checked (``spec``), the tasks it names with their
identities (``tasks``), what they cost (``calibration``: the calibrated model and its file;
``costmodel``: its correction learnt from a store's finished tasks), and the finite-size table's
keys, fit range and precision targets a spec names (``targets``). Imports nothing else of the
package but ``campaign.errors``."""
