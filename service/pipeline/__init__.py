"""The request pipelines, above the stages they call: a ``/v1/predict`` request from read stacks to
poses (:mod:`service.pipeline.predict`); the API turns their plain results into responses."""
