"""The `jaxnh` command line (`jaxnh demo | fit | design`); its implementation is `jaxnh._cli`."""

from jaxnh._cli.main import main as main


__all__ = ["main"]


if __name__ == "__main__":
    raise SystemExit(main())
