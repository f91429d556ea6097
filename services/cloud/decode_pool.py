"""Keyframe features decoded in helper processes (``ProcessConfig.decode_workers``).

The cloud's worker applies the edges' messages in turn on one thread. A keyframe's features
are standalone (``common.codec.frames.KIND_STANDALONE_KEYFRAME``), so any process can decode
them: :class:`DecodePool` decodes them on the event loop's side, before the message reaches
the worker, which takes the result through ``KeyframeDecoders.offer``. What the pool cannot
decode (no pool, a broken pool, a bad payload) the worker decodes, and refuses, as before.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

from common.codec.errors import CodecError
from common.codec.types import CodecConfig, KeyframeFeatures
from common.links.edge_cloud import KeyframeUpdate, KeyframeUpdateCoded
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.cloud.child_process import child_process_init
from services.cloud.fusion.uplink import KeyframeDecoders

log = logging.getLogger(__name__)

Predecoded = tuple[bytes, CodecConfig, KeyframeFeatures]
"""A keyframe payload, the codec config and the features a decode process made of it."""


_PROCESS_DECODERS: KeyframeDecoders | None = None


def decode_process_init(parent_pid: int, vocabulary: Vocabulary) -> None:
    """Initializer of a decode process (``ProcessPoolExecutor(initializer=...)``): the
    service's lifecycle (:func:`child_process_init`) and this vocabulary."""
    global _PROCESS_DECODERS
    child_process_init(parent_pid)
    _PROCESS_DECODERS = KeyframeDecoders(vocabulary)


def decode_in_process(payload: bytes, config: CodecConfig) -> KeyframeFeatures | None:
    """The keyframe features of ``payload`` in a decode process (None: not a keyframe
    payload, or it fails to decode; the worker then decodes it and reports why)."""
    if _PROCESS_DECODERS is None:
        raise RuntimeError("decode_in_process outside a decode process")
    try:
        out = _PROCESS_DECODERS.decode(payload, config)
    except CodecError:
        return None
    return out if isinstance(out, KeyframeFeatures) else None


class DecodePool:
    """``workers`` spawned decode processes holding ``vocabulary`` (0: none, and
    :meth:`predecode` returns None)."""

    def __init__(self, workers: int, vocabulary: Vocabulary) -> None:
        self._pool: ProcessPoolExecutor | None = None
        if workers:
            self._pool = ProcessPoolExecutor(
                workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=decode_process_init,
                initargs=(os.getpid(), vocabulary),
            )

    async def predecode(
        self, message: Message, codec_of: Callable[[str], CodecConfig]
    ) -> Predecoded | None:
        """``message``'s keyframe features decoded with its robot's codec (``codec_of(robot
        name)``) in a decode process. None: no pool, not a keyframe with features, it did not
        decode, or the pool broke (then the pool is dropped and the worker decodes from here
        on)."""
        pool = self._pool
        if pool is None or not isinstance(message, KeyframeUpdate | KeyframeUpdateCoded):
            return None
        if not message.features:
            return None
        config = codec_of(str(message.agent_id))
        try:
            loop = asyncio.get_running_loop()
            feats = await loop.run_in_executor(pool, decode_in_process, message.features, config)
        except (BrokenExecutor, OSError, RuntimeError) as exc:
            log.warning("decode process failed (%s); decoding on the worker", exc)
            self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            return None
        return None if feats is None else (message.features, config, feats)

    def shutdown(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
