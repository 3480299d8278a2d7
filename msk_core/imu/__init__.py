"""IMU kinematics: orientations to joint angles offline (:mod:`.kinematics`), which segments give which pack
coordinates (:mod:`.mapping`), and the live, streaming version (:mod:`.stream`)."""
