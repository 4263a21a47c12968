"""`usvc` command line: localize one photo against a map, and rebuild the shipped encoders."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import fields
from pathlib import Path

from usvc.errors import UsvcError
from usvc.model.errors import ModelError

log = logging.getLogger("usvc")


def _pretrain(args: argparse.Namespace) -> int:
    from usvc.training.encoder_file import save_encoder_weights
    from usvc.training.pretrain import PretrainOptions, pretrain_encoder

    known = {f.name for f in fields(PretrainOptions)}
    overrides = {}
    for item in args.set or []:
        key, _, value = item.partition("=")
        if key not in known:
            raise UsvcError(f"pretrain-encoder: unknown option {key!r}; known: {', '.join(sorted(known))}")
        kind = type(getattr(PretrainOptions(), key))
        overrides[key] = kind(value)
    opts = PretrainOptions(encoder_width=args.width, **overrides)
    encoder, provenance = pretrain_encoder(opts, device=args.device)
    provenance["command"] = " ".join(["usvc", *sys.argv[1:]])
    record = save_encoder_weights(Path(args.out), encoder, provenance)
    print(json.dumps({k: record[k] for k in ("file", "width", "fingerprint", "megabytes",
                                             "loss_first_100", "loss_last_100", "train_seconds")}))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usvc", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at DEBUG level")
    sub = parser.add_subparsers(dest="command", required=True)

    pre = sub.add_parser("pretrain-encoder", help="pretrain an encoder on generated rooms (rebuilds weights/)")
    pre.add_argument("--width", type=float, default=1.0, help="channel multiplier (0.5 = model=small)")
    pre.add_argument("--out", required=True, help="weight file to write (.pt); provenance goes to .json beside it")
    pre.add_argument("--device", default="cpu")
    pre.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="override a PretrainOptions field, e.g. --set iterations=2000")
    pre.set_defaults(run=_pretrain)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.run(args))
    except (UsvcError, ModelError) as err:
        print(f"usvc {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
