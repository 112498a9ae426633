"""The pure numerical core: plant model, planning, tracker synthesis, observer, control law,
plant physics and offline simulation. No clocks, sockets, files or globals live here; randomness
comes in as a ``numpy.random.Generator``.
"""
