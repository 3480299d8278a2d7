"""Device protocols (Delsys Trigno TCP SDK, Xsens Xbus) and faithful simulators of the devices.

Drivers turn device bytes into plain Python/numpy records; the Zenoh nodes in ``services`` publish them.
"""
