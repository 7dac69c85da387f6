"""The camera and its set-up: the array's geometry and homographies, the lens PSF, the sensor, the rig file
and its checks, and the camera set-up and the system-design quantities."""
