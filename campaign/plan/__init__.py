"""The plan: a campaign spec parsed and checked (``spec``), the tasks it names with their
identities (``tasks``), and what they cost (``costmodel``). Imports nothing else of the package
but ``campaign.errors``."""
