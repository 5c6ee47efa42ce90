"""The live server of one mesh run: a foxglove-sdk WebSocket server.

    python -m diskf_mesh.live.server PORT     (``world --live PORT`` starts it)

It is the recorder's writer (``recording.writer.TickWriter``) with a Foxglove
WebSocket server in place of the MCAP file: the world hands it every closed
tick through a pipe, exactly as it hands them to the recorder
(``LiveFeed``), so the world's tick costs a pickle and a pipe write and
nothing here runs under the world's interpreter lock. It publishes every
channel of a recording, with the same topics, schemas and messages
(``recording.schemas``; ``/scene`` as foxglove-sdk's ``SceneUpdate``, here
with every tick), so Foxglove or Lichtblick opens a running mesh as it
opens a recording. ``/run`` (once, first, in a recording) goes again every
``RUN_EVERY_S`` for the clients that came later. While no client subscribes
to any channel, the server skips the ticks (it reads them off the pipe and
nothing more), so a live run nobody watches costs a pipe write a tick. It
listens on 127.0.0.1 only and ends when the world closes the pipe.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import foxglove

from diskf_mesh.recording.writer import NICE, PIPE_BYTES, Recorder, TickWriter, _frames

HOST = "127.0.0.1"
NAME = "diskf-mesh"
RUN_EVERY_S = 1.0


def url(port: int) -> str:
    """The address Foxglove or Lichtblick opens (Open connection, Foxglove WebSocket)."""
    return f"ws://{HOST}:{port}"


class Sink:
    """The methods of ``mcap.writer.Writer`` that ``TickWriter`` calls, onto
    the channels of a foxglove-sdk context (attachments and metadata are
    the file's: a live client gets ``/run``)."""

    def __init__(self, context: foxglove.Context):
        self.context = context
        self._schemas, self._channels = [], []
        self._run, self._run_due = None, 0.0  # /run's (channel, data, log time), when it goes again

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        self._schemas.append(foxglove.Schema(name=name, encoding=encoding, data=data))
        return len(self._schemas)

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata=None) -> int:
        self._channels.append(foxglove.Channel(topic, schema=self._schemas[schema_id - 1],
                                               message_encoding=message_encoding, context=self.context))
        return len(self._channels)

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        channel = self._channels[channel_id - 1]
        if channel.topic() == "/run":
            self._run = (channel, data, log_time)
        elif self._run is not None and time.monotonic() >= self._run_due:
            self._run_due = time.monotonic() + RUN_EVERY_S
            self._run[0].log(self._run[1], log_time=self._run[2])
        channel.log(data, log_time=log_time)

    def watched(self) -> bool:
        """Whether a client subscribed to any channel."""
        return any(channel.has_sinks() for channel in self._channels)

    def start(self, *args, **kwargs) -> None:
        pass

    add_attachment = add_metadata = flush = finish = start


class LiveFeed(Recorder):
    """The world's side: ``Recorder``'s hooks, feeding the live server
    process on ``port`` instead of the writer (``path`` names the server)."""

    def __init__(self, port: int, trace, scn, **run):
        self.port = int(port)
        super().__init__(url(port), trace, scn, **run)

    def _spawn(self) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", __spec__.name if __spec__ else "diskf_mesh.live.server",
                                 str(self.port)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)


def serve(port: int, pipe: int = 0) -> int:
    """Frames from ``pipe`` (``LiveFeed``) onto the server, until the pipe's
    end. Its last act is ``{"written": the last tick published, "error":
    null}`` on standard output (``Recorder.finish`` reads it)."""
    for sig in (signal.SIGINT, signal.SIGTERM):  # the world's to handle: its end closes the pipe
        signal.signal(sig, signal.SIG_IGN)
    try:
        os.nice(NICE)  # the lockstep's processes first, as the recorder's writer
    except OSError:
        pass
    context = foxglove.Context()
    sink = Sink(context)
    try:
        server = foxglove.start_server(name=NAME, host=HOST, port=port, context=context)
    except RuntimeError as e:  # the port was taken after the world checked it: the run goes on unwatched
        print(f"error: live: cannot serve on {url(port)}: {e}", file=sys.stderr, flush=True)
        return 1
    writer, buf, written = None, bytearray(), 0
    try:
        while chunk := os.read(pipe, PIPE_BYTES):
            buf += chunk
            for item in _frames(buf):
                if item[0] == "start":
                    writer = TickWriter(sink, **item[1], mcap=sink, scene_each_tick=True)
                elif item[0] == "tick":
                    if sink.watched():
                        writer.write_tick(*item[1:])
                    written = item[1]
                elif item[0] == "finish":
                    writer.finish(*item[1:])
    finally:
        server.stop()
    os.write(1, (json.dumps({"written": written, "error": None}) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(serve(int(sys.argv[1])))
