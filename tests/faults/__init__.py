"""Faults on the real bench: the plant is kept safe and no recorded data is lost.

Every test here starts its own processes on its own interface-local bus group (``ff11::``, made
private by :func:`isolated_group`) and port, so tests never hear each other, and every one of
them is bounded in count and in time. The test process itself joins the group as a listening
node (:class:`BusWatch`): it sees what the emulator and the daemon put on the bus, with the
kernel's receive time stamps, which is how a kill is timed and how the plant's side is observed.

The bench runs use the paper's set-up as it is (the time-optimal path), real-time ones with
the two bench processes at SCHED_FIFO priority (``realtime_priority``, as bench/bench.py runs
them) where the system permits it: this machine is shared, and what a test measures must be
the fault it injects, not another job's load (measured: with other jobs running, an
unprioritised flooded run once lost 14 % of its periods). The flood helper and the test's
listener run at normal priority. The command-line fuzzing runs ``plan`` in-process on the
rate-limited path, which plans in microseconds.

What the bus faults can and cannot show:

- Sensor frame loss is visible to the controller (the rolling counter: ``sensor_frames_lost``,
  coasted cycles). Command frame loss is not, by design: the sensor frame carries no command
  acknowledgement, and a real-time plant simply holds the last voltage (a DAC) for another
  period. Its effect is observable as the emulator's own count of dropped commands, as the
  absence of watchdog trips (the status bit recorded on ``/sensor``) and as the settle time.
- A foreign frame that carries a *valid* E2E CRC for one of our standard ids is spoofing, which
  a CRC-16 does not defend against; the flood therefore makes its bad CRCs bad on purpose.
"""
