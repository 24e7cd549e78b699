"""`smana bench <name>`: one benchmark per module, each running smana beside the peer a user
would pick instead, on the same input in the same process."""
