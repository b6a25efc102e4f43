"""Recorded robot datasets: LeRobot's layouts read with pyarrow and PyAV (no torch), explained into maps datasets on
one machine or a Ray cluster, and their maps viewed, rendered and measured. The top room below the command line:
nothing else in the package imports it."""
