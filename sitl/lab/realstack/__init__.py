"""The real PX4 and ArduCopter SITL in the lab: start them, fly them from a
ground station, and fly the companion beside them (:mod:`.launch`, :mod:`.gcs`)."""
