"""`python -m fcnpose_tf` is the same as the `fcnpose-tf` command."""

from fcnpose_tf.console import main

raise SystemExit(main())
