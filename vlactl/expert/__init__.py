"""Scripted expert that solves LIBERO pick-and-place tasks from the simulator's privileged object poses."""
