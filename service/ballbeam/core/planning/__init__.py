"""The plan shape every planner returns (`plan.py`) and the planners: bang-bang,
servo-rate-limited and full-model time-optimal paths.
"""
