"""CiA 402 in one place: objects, controlword commands, statusword states, the transition table, modes.

Shared by the master (driver/canopen_axis.py) and the emulated drive (plant_emulator/node402.py): no
CiA 402 number appears anywhere else. Both sides step their state machine once per cycle from
tables, never by blocking.
"""

from __future__ import annotations

from enum import Enum, IntEnum

# -- objects (CiA 301 communication + CiA 402 drive profile) ---------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COB_ID_SYNC = 0x1005
COMM_CYCLE_PERIOD = 0x1006  # us
CONSUMER_HEARTBEAT_TIME = 0x1016  # sub n: (node id << 16) | time in ms
PRODUCER_HEARTBEAT_TIME = 0x1017  # ms
IDENTITY = 0x1018  # 1 vendor, 2 product, 3 revision, 4 serial
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
ABORT_CONNECTION_OPTION = 0x6007  # what the drive does when it loses the master (heartbeat)
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064  # counts
FOLLOWING_ERROR_WINDOW = 0x6065  # counts
FOLLOWING_ERROR_TIMEOUT = 0x6066  # ms
VELOCITY_ACTUAL = 0x606C  # counts/s
TARGET_TORQUE = 0x6071  # per mille of rated
MAX_TORQUE = 0x6072  # per mille of rated
RATED_TORQUE = 0x6076  # mN m (here: milli effort units, mN or mV)
TORQUE_ACTUAL = 0x6077  # per mille of rated
SOFTWARE_POSITION_LIMIT = 0x607D  # 1 min, 2 max, counts
DIGITAL_INPUTS = 0x60FD  # bit 0 negative limit, 1 positive limit, 2 home switch (optional object)
SUPPORTED_DRIVE_MODES = 0x6502

#: CiA 402 device type: profile 402 (servo drive)
DEVICE_TYPE_SERVO = 0x00020192


class Mode(IntEnum):
    """Modes of operation (0x6060 / 0x6061) the drive can report; drivectl commands CST."""

    NONE = 0
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


#: 0x6502 bit of each mode (bit n-1 for mode n)
def supported_mode_bit(mode: Mode) -> int:
    return 1 << (int(mode) - 1)


class Command(IntEnum):
    """Controlword commands (bits 0-3 and 7)."""

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080  # acts on the rising edge of bit 7


HALT_BIT = 0x0100  # controlword bit 8: halt (the drive holds zero torque in CST)


class PowerState(Enum):
    """The power states of the CiA 402 drive state machine."""

    NOT_READY_TO_SWITCH_ON = "Not Ready To Switch On"
    SWITCH_ON_DISABLED = "Switch On Disabled"
    READY_TO_SWITCH_ON = "Ready To Switch On"
    SWITCHED_ON = "Switched On"
    OPERATION_ENABLED = "Operation Enabled"
    QUICK_STOP_ACTIVE = "Quick Stop Active"
    FAULT_REACTION_ACTIVE = "Fault Reaction Active"
    FAULT = "Fault"


#: the states the per-cycle paths compare against, as module constants: on Python 3.11 a member read through
#: its class (``PowerState.FAULT``) goes through EnumType's ``__getattr__`` hook, some 0.3 us a read
POWER_OPERATION_ENABLED = PowerState.OPERATION_ENABLED
POWER_FAULT = PowerState.FAULT


#: statusword (mask, value) of each state, CiA 402 table 30
_SW_PATTERNS: tuple[tuple[int, int, PowerState], ...] = (
    (0x4F, 0x00, PowerState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, PowerState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, PowerState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, PowerState.SWITCHED_ON),
    (0x6F, 0x27, PowerState.OPERATION_ENABLED),
    (0x6F, 0x07, PowerState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, PowerState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, PowerState.FAULT),
)

#: statusword bits 0-6 a drive reports in each state (bit 4 voltage enabled set where power is on)
_SW_BITS = {
    PowerState.NOT_READY_TO_SWITCH_ON: 0x00,
    PowerState.SWITCH_ON_DISABLED: 0x40,
    PowerState.READY_TO_SWITCH_ON: 0x21,
    PowerState.SWITCHED_ON: 0x33,
    PowerState.OPERATION_ENABLED: 0x37,
    PowerState.QUICK_STOP_ACTIVE: 0x17,
    PowerState.FAULT_REACTION_ACTIVE: 0x1F,
    PowerState.FAULT: 0x08,
}
#: the same by the state's value: a str key hashes in C, a PowerState key calls Enum.__hash__ (every cycle)
_SW_BITS_BY_VALUE = {state.value: bits for state, bits in _SW_BITS.items()}

SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800
SW_FOLLOWS_COMMAND = 0x1000  # CST: the drive follows the target torque


def _decode_bits(bits: int) -> PowerState:
    for mask, value, state in _SW_PATTERNS:
        if bits & mask == value:
            return state
    return PowerState.NOT_READY_TO_SWITCH_ON


#: every pattern's mask lies within 0x6F, so the state depends on those bits only: the table for each of
#: their values, made once from _SW_PATTERNS (decoded every cycle)
_SW_MASK = 0x6F
assert all(mask | _SW_MASK == _SW_MASK for mask, _, _ in _SW_PATTERNS)
_SW_DECODED = tuple(_decode_bits(bits) for bits in range(_SW_MASK + 1))


def decode_statusword(sw: int) -> PowerState:
    return _SW_DECODED[sw & _SW_MASK]


def encode_statusword(state: PowerState, *, remote: bool = True, follows: bool = False,
                      warning: bool = False, internal_limit: bool = False) -> int:
    sw = _SW_BITS_BY_VALUE[state._value_]
    if remote:
        sw |= SW_REMOTE
    if follows:
        sw |= SW_FOLLOWS_COMMAND
    if warning:
        sw |= SW_WARNING
    if internal_limit:
        sw |= SW_INTERNAL_LIMIT
    return sw


def decode_command(cw: int) -> Command | None:
    """The device-control command in a controlword (bits 0-3; bit 7 is the fault-reset edge)."""
    if cw & 0x0002 == 0:
        return Command.DISABLE_VOLTAGE
    if cw & 0x0006 == 0x0002:
        return Command.QUICK_STOP
    if cw & 0x0007 == 0x0006:
        return Command.SHUTDOWN
    if cw & 0x000F == 0x0007:
        return Command.SWITCH_ON
    if cw & 0x000F == 0x000F:
        return Command.ENABLE_OPERATION
    return None


# -- the drive's side: transitions caused by a command (CiA 402 figure 30) ------------------------
S = PowerState
C = Command
#: (state, command) -> next state; commands absent for a state leave it where it is
DRIVE_TRANSITIONS: dict[tuple[PowerState, Command], PowerState] = {
    (S.SWITCH_ON_DISABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 2
    (S.READY_TO_SWITCH_ON, C.SWITCH_ON): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 3 + 4
    (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 7
    (S.SWITCHED_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 4
    (S.SWITCHED_ON, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 6
    (S.SWITCHED_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, C.SWITCH_ON): S.SWITCHED_ON,  # 5 (disable operation)
    (S.OPERATION_ENABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 9
    (S.OPERATION_ENABLED, C.QUICK_STOP): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 12
    (S.QUICK_STOP_ACTIVE, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 16
}


# -- the master's side: which command moves a drive towards a target state -------------------------
#: (current, target) -> command to send this cycle; None = wait (the drive moves on its own)
MASTER_PATH: dict[tuple[PowerState, PowerState], Command | None] = {
    # enable: 2, then 3+4 in one command
    (S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED): C.SHUTDOWN,
    (S.READY_TO_SWITCH_ON, S.OPERATION_ENABLED): C.ENABLE_OPERATION,
    (S.SWITCHED_ON, S.OPERATION_ENABLED): C.ENABLE_OPERATION,
    (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED): C.DISABLE_VOLTAGE,  # through Switch On Disabled
    (S.FAULT, S.OPERATION_ENABLED): None,  # never reset a fault implicitly: see MasterStateMachine
    (S.NOT_READY_TO_SWITCH_ON, S.OPERATION_ENABLED): None,
    (S.FAULT_REACTION_ACTIVE, S.OPERATION_ENABLED): None,
    # disable
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): C.DISABLE_VOLTAGE,
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED): C.DISABLE_VOLTAGE,
    (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED): C.DISABLE_VOLTAGE,
    (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED): C.DISABLE_VOLTAGE,
    (S.FAULT, S.SWITCH_ON_DISABLED): None,
    (S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): None,
    (S.FAULT_REACTION_ACTIVE, S.SWITCH_ON_DISABLED): None,
    # quick stop (only from Operation Enabled; elsewhere the drive is not producing torque anyway)
    (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE): C.QUICK_STOP,
}
del S, C


def next_command(current: PowerState, target: PowerState) -> Command | None:
    """The command that moves a drive from ``current`` towards ``target`` (None: nothing to send)."""
    if current is target:
        return None
    return MASTER_PATH.get((current, target))


# -- error codes (0x603F, CiA 402 / CiA 301 emergency codes) -----------------------------------------
ERROR_TEXT = {
    0x0000: "no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x4310: "drive temperature too high",
    0x5441: "limit switch (positive)",
    0x5442: "limit switch (negative)",
    0x7305: "incremental sensor 1 fault (encoder)",
    0x8110: "CAN overrun (objects lost)",
    0x8100: "communication error (NMT took the drive out of Operational)",
    0x8130: "life guard or heartbeat error (master lost)",
    0x8210: "PDO not processed (length error)",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout (the master's setpoint came too late)",
    0x8611: "following error",
    0x8612: "reference limit (software position limit)",
    0xFF00: "emulator: injected fault",
}


HEARTBEAT_LOST_ERROR = 0x8130


def error_text(code: int) -> str:
    if code in ERROR_TEXT:
        return ERROR_TEXT[code]
    return f"error 0x{code:04X} (manufacturer or unknown)"


# -- the master's controlword, stepped once per cycle ---------------------------------------------------
#: the command that holds a state once it is the target
_HOLD = {
    PowerState.OPERATION_ENABLED: Command.ENABLE_OPERATION,
    PowerState.SWITCH_ON_DISABLED: Command.DISABLE_VOLTAGE,
    PowerState.QUICK_STOP_ACTIVE: Command.QUICK_STOP,
    PowerState.READY_TO_SWITCH_ON: Command.SHUTDOWN,
    PowerState.SWITCHED_ON: Command.SWITCH_ON,
}


class MasterStateMachine:
    """Which controlword to send this cycle to bring a drive to ``target`` (non-blocking).

    One call per cycle with the state decoded from the latest statusword. A fault is never reset
    implicitly: only after ``request_fault_reset()``, as a rising edge of bit 7 (bit 7 low, then
    high), verified by the drive leaving Fault (``reset_attempts`` counts the edges, so a caller can
    give up and report). The halt bit is set
    unless the drive is enabled and meant to be: a drive never moves on a stale setpoint while it
    is being switched on.
    """

    def __init__(self, target: PowerState = PowerState.SWITCH_ON_DISABLED):
        self.target = target
        self.reset_attempts = 0
        self.reset_requested = False
        self._last_cw = 0
        self._held: PowerState | None = None

    def request_fault_reset(self) -> None:
        """Reset a fault (edge on the next cycles), then stay in Switch On Disabled."""
        self.reset_requested = True
        self.target = PowerState.SWITCH_ON_DISABLED

    def controlword(self, state: PowerState) -> int:
        if state is self.target and state is not POWER_FAULT and self._held is state:
            return self._last_cw  # steady state, the per-cycle fast path
        self._held = state if state is self.target else None
        if state is PowerState.FAULT and self.reset_requested:
            cmd = Command.FAULT_RESET
        else:
            if state is not PowerState.FAULT:
                self.reset_requested = False
            cmd = next_command(state, self.target)
        if cmd is Command.FAULT_RESET:
            if self._last_cw & Command.FAULT_RESET:
                cw = 0  # bit 7 back low: the next reset is a fresh edge
            else:
                cw = int(Command.FAULT_RESET)
                self.reset_attempts += 1
        else:
            if state is not PowerState.FAULT:
                self.reset_attempts = 0
            if cmd is None:
                cmd = _HOLD.get(state, Command.DISABLE_VOLTAGE) if state is self.target else None
            cw = int(cmd) if cmd is not None else (self._last_cw & 0x000F)
        if not (state is PowerState.OPERATION_ENABLED and self.target is PowerState.OPERATION_ENABLED):
            cw |= HALT_BIT
        self._last_cw = cw
        return cw
