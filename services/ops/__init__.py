"""Operations: the `zetta` command line, the local stack and the harness registry commands.

The one package above both the SDK (`zetta`) and the services: it wires them together."""
