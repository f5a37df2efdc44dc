"""A section of the reducer: what it declares (``Section``), a group it adds to /reduced (``Group``).

A section is a statistic beyond the finite-size table: the variants compared (``tradeoff``), the
physical systems (``systems``), the jamming point and the protocols compared (``protocols``), the
linear response (``response``). Its module ends with ``SECTION = Section(...)``, which names the
section and says when it is computed, how, and what it adds to each output; the reducer
(``campaign.results.reduce.SECTIONS``, the registry), the writer (``campaign.report.writing``) and
``campaign reduce``'s console text go through the registry, and ``campaign.report.sectionplots``
holds its figures under its name. Every hook but ``compute`` takes the section's result (what
``compute`` returned, ``Reduction.sections[name]``) and is pure: text is returned as strings, and
``campaign.report`` writes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable


def _always(table) -> bool:
    return True


def _nothing(result) -> dict:
    return {}


def _silent(result) -> str:
    return ""


@dataclass(frozen=True)
class Group:
    """A group of /reduced: its columns (records, a list of dicts, or name -> array; None: a group
    that holds groups) and its attributes."""

    columns: Any = None
    attrs: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Section:
    """An optional part of a reduction and what it adds to each output (the module docstring).

    ``compute(table, settings, distributions)``: the section's result, from the reducer's
    ``Table`` (the cells, fits, ``N_G -> inf`` row, systems and notes: a note is appended to
    ``table.notes``), its ``Settings`` and the summed histograms; called when ``present(table)``,
    else the result is ``empty()``. From the result: ``tables`` the CSVs written into every output
    directory, empty when the section has nothing (before ``summary.json``); ``files`` the
    section's own files, written when it has something (after ``summary.json``); ``reduced`` its
    groups of /reduced by path (``{"protocols/values": Group(...)}``, in the order they are made);
    ``console`` what ``campaign reduce`` prints after the finite-size table ("" prints nothing);
    ``json`` its keys of ``summary.json``."""

    name: str
    compute: Callable
    present: Callable = _always
    empty: Callable = list
    tables: Callable = _nothing
    files: Callable = _nothing
    reduced: Callable = _nothing
    console: Callable = _silent
    json: Callable = _nothing
