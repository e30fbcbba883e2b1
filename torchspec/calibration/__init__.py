"""What a capture's files do not say, estimated from photographs: the lights' gains and positions
(:mod:`~torchspec.calibration.lights`), the light's kernel from a mirror
(:mod:`~torchspec.calibration.kernel`), light directions from a chrome sphere
(:mod:`~torchspec.calibration.sphere`), the camera's response (:mod:`~torchspec.calibration.response`,
judged by :mod:`~torchspec.calibration.response_judge`) and frames out of line with their
neighbours (:mod:`~torchspec.calibration.brightness`)."""
