"""``pmvir serve --host H --port P``: the capture-processing HTTP API (uvicorn).

Configuration comes from the ``PMVIR_*`` environment variables (README,
"Service"). The app is named by its import string, so the library itself
never imports the service.
"""

from __future__ import annotations

import argparse

from pmvir.errors import ConfigError

APP = "service.app:create_app"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the HTTP API of the capture-processing service",
        description="Serve the /v1 API (FastAPI under uvicorn). Needs Redis (PMVIR_REDIS_URL), a storage "
        "root (PMVIR_STORAGE) and API keys (PMVIR_API_KEYS); run `pmvir worker` beside it.",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (default 1)")
    p.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    p.add_argument(
        "--proxy-headers",
        action="store_true",
        help="trust X-Forwarded-* from the addresses in FORWARDED_ALLOW_IPS (behind a proxy)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        import uvicorn
    except ImportError as exc:
        raise ConfigError("pmvir serve needs the service extras: pip install 'pmvir[service]'") from exc
    if not 0 < args.port < 65536:
        raise ConfigError(f"--port must be 1..65535, got {args.port}")
    uvicorn.run(
        APP,
        factory=True,
        host=args.host,
        port=args.port,
        workers=args.workers,
        log_level=args.log_level,
        proxy_headers=args.proxy_headers,
    )
    return 0
