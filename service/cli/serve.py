"""``kincal demo``, ``kincal serve`` and ``kincal keys``: the HTTP service."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from solver.errors import KincalError


def demo(
    output_dir: Annotated[Path, typer.Option(help="Where the demo writes its files.")] = Path(
        "out/demo"
    ),
) -> None:
    """Simulate a Jaco2 recording like the paper's, calibrate it, print Table II."""
    from service.cli.demo import run_demo

    run_demo(output_dir, echo=typer.echo)


def settings_epilog() -> str:
    """Every service setting as the environment variable that sets it, with its default
    (from :class:`service.settings.Settings`, through :mod:`service.cli.generated_help`)."""
    from service.cli.generated_help import SERVE_SETTINGS

    return "\n\n".join(SERVE_SETTINGS)  # one paragraph per line: each keeps its own line


def serve(
    host: Annotated[
        str | None, typer.Option(help="Interface [127.0.0.1; keyless only on loopback].")
    ] = None,
    port: Annotated[int | None, typer.Option(min=1, max=65535, help="Port [8000].")] = None,
) -> None:
    """Run the HTTP service (other settings: the KINCAL_* environment variables below)."""
    from service.jobs.supervisor import run_server

    raise typer.Exit(run_server(host=host, port=port, announce=_announce))


def _announce(text: str) -> None:
    typer.echo(text)  # stdout, flushed: a script waiting for the service reads it at once


keys_app = typer.Typer(no_args_is_help=True, help="API keys of the HTTP service.")


@keys_app.command("create")
def keys_create(
    tenant: Annotated[str, typer.Option(help="Tenant the key acts for (created if new).")],
) -> None:
    """Create an API key: printed once, only its SHA-256 is stored."""
    from service.security import create_key

    key_id, key = create_key(tenant)
    typer.echo(key)
    typer.echo(f"key {key_id} for tenant {tenant}; it is not shown again", err=True)


@keys_app.command("revoke")
def keys_revoke(key_id: Annotated[str, typer.Argument(help="The key id (kc_<id>_...).")]) -> None:
    """Revoke an API key (services stop accepting it within KINCAL_API_KEY_CACHE_S)."""
    from service.security import revoke_key

    if not revoke_key(key_id):
        raise KincalError(f"no active key with id {key_id!r}")
    typer.echo(f"revoked key {key_id}")
