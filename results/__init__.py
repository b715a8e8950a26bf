"""Tidy episode tables: schema, storage, aggregation (and later leaderboards, gates, plots)."""
