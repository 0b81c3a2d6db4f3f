"""What the tests share: brokers and engines as processes, vehicles, waits, collectors."""
