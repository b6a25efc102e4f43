"""Readers for robot datasets on disk (LeRobot's layouts), with numpy, pyarrow and PyAV only."""
