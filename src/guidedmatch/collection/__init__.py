"""Matching whole image collections (issue 12): feature sources, pair lists, sinks and the scheduling engine."""
