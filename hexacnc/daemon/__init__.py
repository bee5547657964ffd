"""The daemon: hot loop process (:mod:`.loop`), supervisor (:mod:`.core`), IPC (:mod:`.shm`), socket server."""
