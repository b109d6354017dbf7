"""Where the viewer is served and how it draws (no viser import: `dyngs-train` reads
these flags without loading the web server), and the check that its port is free."""

from __future__ import annotations

import errno
import math
import socket
from dataclasses import dataclass

from dyngs.errors import ConfigError, UserError


class PortTaken(UserError):
    """The viewer's port is in use."""


@dataclass(frozen=True)
class ViewerOptions:
    """Where the page is served and how frames are drawn."""

    host: str = "localhost"
    """Address to serve on: `localhost` keeps the viewer on this machine.
    `0.0.0.0` serves it to every network the machine is on."""
    port: int = 8080
    """Port to serve on (0: any free port; the URL printed says which)."""
    max_side: int = 800
    """Long side, in pixels, of the frame drawn once the view stops moving.
    (At most the browser's canvas; smaller frames are drawn while it moves.)"""
    target_fps: float = 12.0
    """Frame rate the adaptive resolution aims at while the view moves or time plays."""
    jpeg_quality: int = 90
    """JPEG quality of the frames sent to the browser (1–100)."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"--port must be in 0..65535, got {self.port}")
        if self.max_side < 16:
            raise ConfigError(f"--max-side must be ≥ 16, got {self.max_side}")
        if not (math.isfinite(self.target_fps) and self.target_fps > 0):
            raise ConfigError(f"--target-fps must be positive, got {self.target_fps}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"--jpeg-quality must be in 1..100, got {self.jpeg_quality}")


def port_taken(host: str, port: int) -> PortTaken:
    return PortTaken(
        f"cannot serve the viewer on {host}:{port}: the port is in use "
        f"(another viewer?); choose another with --port"
    )


def check_port(host: str, port: int) -> None:
    """Raise `PortTaken` when `port` cannot be bound on `host` (viser would quietly move
    to the next free port, and the printed address would be wrong)."""
    if port == 0:
        return
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as error:
        raise ConfigError(f"--host {host}: {error.strerror}") from None
    for family, kind, proto, _, address in addresses:
        with socket.socket(family, kind, proto) as probe:
            # As the server will: a port left in TIME_WAIT by a closed viewer is free.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(address)
            except OSError as error:
                if error.errno == errno.EADDRINUSE:
                    raise port_taken(host, port) from None
                # Another error (an IPv6 address on a machine without IPv6): the server
                # will skip that address too.
