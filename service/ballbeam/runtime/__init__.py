"""Thin imperative edges: frames, bus, ticker, recorder, daemon, launcher."""
