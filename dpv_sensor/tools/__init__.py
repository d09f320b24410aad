"""Console tools (`ros2 run dpv_sensor <tool>`)."""
from __future__ import annotations

import sys
from typing import List, Optional


def tool_argv(argv: Optional[List[str]] = None) -> List[str]:
    """The tool's own arguments: `ros2 run` may append `--ros-args ...`, which these tools do not use."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
