"""MAVLink telemetry for ngnav (pymavlink); empty until the telemetry issue lands."""
