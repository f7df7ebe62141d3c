"""The SVRnet service: from uploaded stacks to each slice's pose in the atlas space.

Importing it turns onnxruntime's own telemetry off (``ORT_DISABLE_TELEMETRY=1``, which onnxruntime
reads once, when it is first imported): its POSIX builds otherwise keep a device id and a queue of
usage events (model files' names, the interpreter's path) under ``~/.cache/Microsoft`` and send
them out, which a hospital's network should not see. A value the environment already sets is kept;
an empty one counts as none (onnxruntime would read it as telemetry on).
"""

import os

if not os.environ.get("ORT_DISABLE_TELEMETRY", "").strip():
    os.environ["ORT_DISABLE_TELEMETRY"] = "1"
