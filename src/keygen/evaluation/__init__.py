"""Evaluation: statistics and (later) rollout runners and reports."""
