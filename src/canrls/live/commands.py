"""Command frames: ``RlsCommand`` in, an action on the pipeline, ``RlsCommandAck`` out.

A command is decoded strictly (:func:`canrls.can.frames.decode_command`), applied
only if it is valid and applicable, and always answered: ``ok``, or why not
(``malformed``, ``unknown_command``, ``unknown_effect``, ``bad_value``,
``not_applicable``, ``disabled``). A rejected command changes nothing.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Sequence

import can

from canrls.can.frames import (
    Command,
    CommandCode,
    CommandFrameError,
    CommandResult,
    EffectId,
    decode_command,
    encode_ack,
)
from canrls.errors import ConfigError
from canrls.estimation.model import Model
from canrls.processor import FrameProcessor

__all__ = ["CommandHandler", "command_effect_name"]

log = logging.getLogger(__name__)


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


class CommandHandler:
    """Applies command frames to a processor's pipeline and acknowledges each.

    :param processor: whose pipeline the commands act on.
    :param enabled: ``[daemon] commands``; False answers every command ``disabled``.
    :param send: sends the acknowledgement (never blocks).
    :param set_model: makes a model the running one (ADD_EFFECT, REMOVE_EFFECT).
    :param on_reset: called after RESET.
    """

    def __init__(self, processor: FrameProcessor, enabled: bool,
                 send: Callable[[Sequence[can.Message]], int],
                 set_model: Callable[[Model, str], None],
                 on_reset: Callable[[], None]) -> None:
        self.processor = processor
        self.enabled = enabled
        self.send = send
        self.set_model = set_model
        self.on_reset = on_reset
        #: commands, commands_rejected
        self.counts: collections.Counter[str] = collections.Counter()
        self._ack_counter = 0

    def handle(self, msg: can.Message) -> CommandResult:
        """Decode, apply and acknowledge one command frame; returns the result sent."""
        self.counts["commands"] += 1
        code = msg.data[0] if len(msg.data) else 0
        try:
            cmd = decode_command(msg)
            code = int(cmd.code)
            if not self.enabled:
                raise CommandFrameError("commands are disabled ([daemon] commands = false)",
                                        CommandResult.DISABLED, code)
            self.apply(cmd)
            result = CommandResult.OK
            log.info("command %s: ok", cmd)
        except CommandFrameError as e:
            result = e.result
            if e.code is not None:
                code = e.code
            self.counts["commands_rejected"] += 1
            log.warning("command frame %s rejected (%s): %s", bytes(msg.data).hex(),
                        result.name.lower(), e)
        self._ack_counter = (self._ack_counter + 1) % 16
        self.send([encode_ack(code, result, self._ack_counter, timestamp=time.time())])
        return result

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
        else:
            self.set_model(self._changed_model(cmd), f"command {cmd}")

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
