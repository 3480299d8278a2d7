"""The processes of the data flow: device drivers, kinematics, estimator, recorder, replayer and the router, on one node runtime."""
