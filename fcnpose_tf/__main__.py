"""`python -m fcnpose_tf` is the same as the `fcnpose-tf` command."""

from fcnpose_tf.cli import console_main

raise SystemExit(console_main())
