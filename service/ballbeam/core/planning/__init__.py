"""Planners: bang-bang, servo-rate-limited and full-model time-optimal paths."""
