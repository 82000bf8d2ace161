"""Command frames: ``RlsCommand`` in, an action on the pipeline, ``RlsCommandAck`` out.

Commands are off unless enabled (``[daemon] commands = true``, ``canrls run
--commands``); off, every frame on the command ID is answered ``disabled``, whatever it
holds. On, a command is decoded strictly (:func:`canrls.can.estimator_frames.decode_command`),
let through a token bucket (``command_rate`` per second, ``command_burst`` at once;
``freeze`` and ``resume`` need no token, :data:`UNLIMITED`), a
changed model is checked before it is applied (at most ``max_parameters``, and its
frames rehearsed), and it is always answered: ``ok``, or why not (``malformed``,
``unknown_command``, ``unknown_effect``, ``bad_value``, ``not_applicable``,
``disabled``, ``too_large``, ``rate_limited``). A rejected command changes nothing.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Sequence

import can

from canrls.can.estimator_frames import (
    Command,
    CommandCode,
    CommandFrameError,
    CommandResult,
    decode_command,
    encode_ack,
)
from canrls.core.effect_names import EffectId
from canrls.core.errors import CanrlsError, ConfigError
from canrls.estimation.model import Model
from canrls.processor import FrameProcessor

__all__ = ["CommandHandler", "TokenBucket", "UNLIMITED", "command_effect_name"]

log = logging.getLogger(__name__)

#: rejected command frames logged per second at most
_LOG_PER_S = 10

#: Commands the token bucket never holds back (nor do they take a token): they grow
#: nothing (no model to rebuild, no state to drop) and cost what any command frame costs
#: (it is decoded and answered whatever the bucket says), while a refusal leaves the
#: estimator in a state the tool did not ask for: a ``resume`` refused after its
#: ``freeze`` left estimation frozen until the tool asked again.
UNLIMITED: frozenset[CommandCode] = frozenset({CommandCode.FREEZE, CommandCode.RESUME})


def command_effect_name(effect: EffectId, order: int, model: Model) -> str:
    """The model's name of the effect a command means: ``cogging:K``, ``user:NAME``...

    :raises CommandFrameError: a user term index the configuration does not have.
    """
    if effect is EffectId.COGGING:
        return f"cogging:{order}"
    if effect is EffectId.USER:
        names = list(model.terms)
        if not 0 < order <= len(names):
            raise CommandFrameError(f"no user term {order} in the configuration "
                                    f"({len(names)} defined)", CommandResult.UNKNOWN_EFFECT)
        return f"user:{names[order - 1]}"
    return effect.effect_name


class TokenBucket:
    """At most ``burst`` commands at once and ``rate`` per second on average.

    :param rate: tokens added per second.
    :param burst: the bucket's depth (and its content at the start).
    """

    def __init__(self, rate: float, burst: int) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.tokens = float(burst)
        self.last: float | None = None

    def take(self, now: float) -> bool:
        """Take one token at time ``now`` [s]; False (nothing taken) when empty."""
        if self.last is not None:
            # tokens <- min(burst, tokens + rate (now - last))
            self.tokens = min(self.burst, self.tokens + self.rate * max(0.0, now - self.last))
        self.last = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class CommandHandler:
    """Applies command frames to a processor's pipeline and acknowledges each.

    :param processor: whose pipeline the commands act on.
    :param enabled: ``[daemon] commands``; False answers every frame ``disabled``.
    :param send: sends the acknowledgement (never blocks).
    :param set_model: makes a model the running one (ADD_EFFECT, REMOVE_EFFECT).
    :param on_reset: called after RESET.
    :param max_parameters: the most parameters a changed model may have (``too_large``).
    :param check_model: raises a :class:`~canrls.core.errors.CanrlsError` for a changed model
        that cannot be published (the frames are rehearsed); called before ``set_model``.
    :param bucket: the rate limit of valid commands (None: none).
    :param save_model: writes the running model and its estimates (SAVE_MODEL; None:
        ``[daemon] saved_model`` is not set, the command is not applicable).
    :param clock: the time the bucket is filled by [s].
    """

    def __init__(self, processor: FrameProcessor, enabled: bool,
                 send: Callable[[Sequence[can.Message]], int],
                 set_model: Callable[[Model, str], None],
                 on_reset: Callable[[], None], *,
                 max_parameters: int | None = None,
                 check_model: Callable[[Model], None] | None = None,
                 bucket: TokenBucket | None = None,
                 save_model: Callable[[], object] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.processor = processor
        self.enabled = enabled
        self.send = send
        self.set_model = set_model
        self.on_reset = on_reset
        self.max_parameters = max_parameters
        self.check_model = check_model
        self.bucket = bucket
        self.save_model = save_model
        self.clock = clock
        #: commands, commands_rejected, and one count per result name (``ok``, ...)
        self.counts: collections.Counter[str] = collections.Counter()
        self._ack_counter = 0
        #: (start of the current second, warnings logged in it, warnings left out)
        self._log_window = (0.0, 0, 0)

    def handle(self, msg: can.Message) -> CommandResult:
        """Decode, apply and acknowledge one command frame; returns the result sent."""
        self.counts["commands"] += 1
        code = msg.data[0] if len(msg.data) else 0
        try:
            if not self.enabled:  # before decoding: whatever the frame holds
                raise CommandFrameError("commands are disabled (enable them with [daemon] "
                                        "commands = true or canrls run --commands)",
                                        CommandResult.DISABLED, code)
            cmd = decode_command(msg)
            code = int(cmd.code)
            b = self.bucket
            if b is not None and cmd.code not in UNLIMITED and not b.take(self.clock()):
                raise CommandFrameError(
                    f"{cmd}: more than {b.burst:g} commands at once or {b.rate:g} per second "
                    f"([daemon] command_burst, command_rate); try again later",
                    CommandResult.RATE_LIMITED, code)
            self.apply(cmd)
            result = CommandResult.OK
            self.counts["ok"] += 1
            log.info("command %s: ok", cmd)
        except CommandFrameError as e:
            result = e.result
            if e.code is not None:
                code = e.code
            self.counts["commands_rejected"] += 1
            self.counts[result.name.lower()] += 1
            self._warn(msg, result, e)
        self._ack_counter = (self._ack_counter + 1) % 16
        self.send([encode_ack(code, result, self._ack_counter, timestamp=time.time())])
        return result

    def _warn(self, msg: can.Message, result: CommandResult, e: CommandFrameError) -> None:
        """Log a rejected frame: at most ``_LOG_PER_S`` a second (a flood must not flood
        the journal too); the first line after a quiet second says how many were left out."""
        now = self.clock()
        start, logged, left_out = self._log_window
        if now - start >= 1.0:
            if left_out:
                log.warning("%d more rejected command frames were not logged", left_out)
            start, logged, left_out = now, 0, 0
        if logged < _LOG_PER_S:
            log.warning("command frame %s rejected (%s): %s", bytes(msg.data).hex(),
                        result.name.lower(), e)
            logged += 1
        else:
            left_out += 1
        self._log_window = (start, logged, left_out)

    def apply(self, cmd: Command) -> None:
        """Apply a valid command; raise CommandFrameError (changing nothing) otherwise."""
        pipe = self.processor.pipeline
        c = cmd.code
        na = CommandResult.NOT_APPLICABLE
        if c is CommandCode.RESET:
            pipe.reset()
            self.on_reset()
        elif c is CommandCode.FREEZE:
            if pipe.frozen:
                raise CommandFrameError("already frozen", na, int(c))
            pipe.freeze()
        elif c is CommandCode.RESUME:
            if not pipe.frozen:
                raise CommandFrameError("not frozen", na, int(c))
            pipe.resume()
        elif c is CommandCode.SET_LAMBDA:
            try:
                pipe.set_lambda(cmd.lam)
            except ConfigError as e:
                raise CommandFrameError(str(e), CommandResult.BAD_VALUE, int(c)) from e
        elif c is CommandCode.SAVE_MODEL:
            if self.save_model is None:
                raise CommandFrameError("no [daemon] saved_model to write the model to", na,
                                        int(c))
            try:
                self.save_model()
            except CanrlsError as e:  # no estimates yet, or the file cannot be written
                raise CommandFrameError(f"save_model: {e}", na, int(c)) from e
        else:
            model = self._changed_model(cmd)
            self._check(cmd, model)
            try:
                self.set_model(model, f"command {cmd}")
            except CanrlsError as e:  # e.g. the estimators cannot be built for it
                raise CommandFrameError(f"{cmd}: {e}", na, int(c)) from e

    def _check(self, cmd: Command, model: Model) -> None:
        """Refuse a changed model the daemon could not publish, before it is applied."""
        n, limit = len(model.parameters), self.max_parameters
        if limit is not None and n > limit:
            raise CommandFrameError(f"{cmd}: the model would have {n} parameters, more than "
                                    f"[daemon] max_parameters = {limit}",
                                    CommandResult.TOO_LARGE, int(cmd.code))
        if self.check_model is not None:
            try:
                self.check_model(model)
            except CanrlsError as e:
                raise CommandFrameError(f"{cmd}: {e}", CommandResult.NOT_APPLICABLE,
                                        int(cmd.code)) from e

    def _changed_model(self, cmd: Command) -> Model:
        """The model with the command's effect added or removed."""
        c = cmd.code
        na = CommandResult.NOT_APPLICABLE
        model = self.processor.model
        name = command_effect_name(cmd.effect, cmd.order, model)
        try:
            if c is CommandCode.ADD_EFFECT:
                if name in model.effect_names:
                    raise CommandFrameError(f"effect {name} is already in the model", na, int(c))
                return model.with_effects(add=[name])
            if name not in model.effect_names:
                raise CommandFrameError(f"effect {name} is not in the model", na, int(c))
            return model.with_effects(remove=[name])
        except ConfigError as e:  # e.g. needs a signal the drive lacks, or no effect left
            raise CommandFrameError(str(e), na, int(c)) from e
