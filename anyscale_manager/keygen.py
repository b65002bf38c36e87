"""anyscale-manager keygen PATH: write a new deployment key (owner-only) for signed layouts."""

import sys

from .protocol_auth import KEY_BYTES, KeyFileError, write_key


def add_arguments(parser) -> None:
    parser.add_argument('path', metavar='PATH',
                        help='the key file to create (refused if it exists); copy it to every '
                             'scale and name it in security.key_file')


def run(args) -> int:
    try:
        write_key(args.path)
    except KeyFileError as e:
        print(f'anyscale-manager keygen: {e}', file=sys.stderr)
        return 2
    print(f'wrote a {KEY_BYTES * 8}-bit key to {args.path} (mode 0600). Copy it to the same '
          'path on every scale (scp -p keeps the mode) and set security.key_file: '
          f'{args.path} in the deployment.')
    return 0
