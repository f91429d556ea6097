"""The three tiers: ``robot``, ``edge`` and ``cloud``. No service imports another."""
