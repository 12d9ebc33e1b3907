"""The render pipeline: check (method tables, plan, cost estimates), the warm session, one-off renders."""
