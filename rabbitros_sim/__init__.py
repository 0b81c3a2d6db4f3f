"""Simulators for tests and benchmarks: a SiK radio pair emulator and a MAVLink vehicle.

They let the engine's MAVLink side be exercised end to end on one machine, over links that
behave like the 433/915 MHz SiK telemetry radios it is meant for (slow, half duplex, lossy),
without hardware.
"""
