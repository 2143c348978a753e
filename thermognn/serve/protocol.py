"""What the serve processes share: the shared-memory layout, field indices and exit reasons.

Pure Python + numpy; imported by the main, physics and haptic processes.
"""

from __future__ import annotations

from .shm import SharedArrays, versioned_layout

# physics -> haptic: local force model, published after every physics step
M_VERSION, M_STEP, M_TIME = 0, 1, 2          # publish counter, physics step id, perf_counter [s]
M_F0 = slice(3, 6)                           # contact force on the user at x0 [N] (model frame)
M_X0 = slice(6, 9)                           # tool position the model was linearised at [m]
M_K = slice(9, 18)                           # stiffness dF/dx, row-major 3x3 [N/m]
M_CONTACT, M_DEPTH = 18, 19                  # contact flag, penetration [m]
MODEL_PAYLOAD = 20

# haptic -> physics: tool state, published every tick
T_TIME = 0                                   # perf_counter [s]
T_X = slice(1, 4)                            # tool centre [m] (model frame)
T_V = slice(4, 7)                            # tool velocity [m/s]
TOOL_PAYLOAD = 7

# control block (each field has a single writer)
C_STOP = 0            # main/physics/haptic: stop requested (reason code, 0 = run)
C_HAPTIC_STATE = 1    # haptic: 0 starting, 1 running, 2 finished
C_PHYSICS_STATE = 2   # physics: 0 starting, 1 running, 2 finished
C_TICKS = 3           # haptic: rows written to the log so far (total, not wrapped)
C_STEPS = 4           # physics: steps taken
C_PHYSICS_T0 = 5      # physics: perf_counter at its first step [s]
C_PHYSICS_T = 6       # physics: perf_counter at its latest step [s]
C_FORCE = 7           # haptic: |force| commanded on the last tick [N]
C_CONTACT = 8         # haptic: contact flag on the last tick
C_FINAL_FORCE = 9     # haptic: |force| commanded on exit (must be 0) [N]
C_LOOP_T0 = 10        # haptic: perf_counter of its first tick [s]
C_ENERGY = 11         # haptic: passivity observer energy [J]
CONTROL_SIZE = 16

# session log, one row per tick (ring buffer)
LOG_COLUMNS = ("t", "x", "y", "z", "fx", "fy", "fz", "physics_step", "contact")
L_T, L_X, L_F, L_STEP, L_CONTACT = 0, slice(1, 4), slice(4, 7), 7, 8

# exit reasons (codes in C_STOP)
REASONS = ("", "duration", "sigint", "sigterm", "physics_crash", "physics_nan", "haptic_nan",
           "device_error", "device_finished", "haptic_crash", "stopped", "main_gone")
REASON_CODE = {r: i for i, r in enumerate(REASONS)}


def make_shared(log_rows: int, create: bool = True, name: str | None = None) -> SharedArrays:
    """The serve block: control, model and tool buffers, session log [log_rows, 9]."""
    layout = {
        "control": (CONTROL_SIZE,),
        "model": versioned_layout(MODEL_PAYLOAD),
        "tool": versioned_layout(TOOL_PAYLOAD),
        "log": (int(log_rows), len(LOG_COLUMNS)),
    }
    return SharedArrays(layout, name=name, create=create)


def request_stop(control, reason: str) -> None:
    """Set the stop reason unless one is already set (first reason wins)."""
    if control[C_STOP] == 0:
        control[C_STOP] = REASON_CODE[reason]


def send_summary(conn, summary: dict) -> None:
    """Hand a child process's summary to the main process; a main process already gone is no error."""
    try:
        conn.send(summary)
    except (BrokenPipeError, OSError):
        pass
