"""The explorer's file input (:class:`Upload`): the browser checks a chosen file's size before
sending anything, so a file above the page's limit is refused in one line instead of being sent
in a websocket message above the server's limit, which closes the page's connection."""
from __future__ import annotations

import base64

import param
from panel.custom import JSComponent

#: The largest file the page takes (bytes); a bigger one is refused before it is sent.
MAX_UPLOAD = 16 * 2**20
#: The server's largest websocket message (bytes): an upload travels as base64 text (4/3 of the
#: file), so every file the page takes fits, with room to spare.
MESSAGE_LIMIT = 2 * MAX_UPLOAD


def mib(size):
    """A size in bytes as the page says it (``31.0 MiB``)."""
    return f"{size / 2**20:.1f} MiB" if size % 2**20 else f"{size // 2**20} MiB"


def upload_refusal(name, size, limit=MAX_UPLOAD):
    """The one line of a file too big for the page (``name``: its name; ``size``: its bytes)."""
    return (f"{name} is {mib(size)}, above the page's upload limit of {mib(limit)}; nothing was sent: "
            f"start the explorer with --data {name} (read on the server), or fit it with pbrdf-cl fit")


class Upload(JSComponent):
    """A file input whose file reaches the server only when it is at most ``limit`` bytes.

    ``filename`` and ``value`` (the bytes; None for an empty file) are set together when a file
    arrives (watch them; choosing the same file again notifies again); a file above the limit is
    not read in the browser: ``refuse(name, size)`` is called on the server instead.

    Parameters
    ----------
    refuse : callable
        Called with the name and the size (bytes) of a file above the limit.
    accept : str
        The file types offered by the browser's dialog (``.csv,.txt``).
    limit : int
        The largest file taken (bytes).
    """

    accept = param.String(default="")
    limit = param.Integer(default=MAX_UPLOAD, bounds=(0, None))
    filename = param.String(default=None, allow_None=True, precedence=-1)
    value = param.Parameter(default=None, precedence=-1)

    _rename = {"filename": None, "value": None}  # the server's: never sent to the browser

    _esm = """
    export function render({ model, el }) {
      const input = document.createElement("input")
      input.type = "file"
      input.accept = model.accept
      input.addEventListener("change", () => {
        const file = input.files.length ? input.files[0] : null
        if (file == null) return
        if (file.size > model.limit) {  // not read, not sent: the server only hears its name and size
          input.value = ""
          model.send_msg({name: file.name, size: file.size})
          return
        }
        const reader = new FileReader()
        reader.onload = () => {
          const url = reader.result, comma = url.indexOf(",")  // data:<type>;base64,<data>
          model.send_msg({name: file.name, size: file.size, data: comma < 0 ? "" : url.slice(comma + 1)})
        }
        reader.readAsDataURL(file)
      })
      el.appendChild(input)
    }
    """

    def __init__(self, refuse, **params):
        super().__init__(**params)
        self.refuse = refuse
        self.on_msg(lambda event: self.receive(event.data))

    def receive(self, msg):
        """A message of the browser: a file (``name``, ``size``, ``data``: base64) or, without
        ``data``, a file above the limit."""
        name, size = str(msg.get("name", "")), int(msg.get("size", 0))
        data = msg.get("data")
        if data is None or size > self.limit:
            self.refuse(name, size)
            return
        value = base64.b64decode(data) or None  # None for an empty file, as Panel's FileInput gives it
        if len(value or b"") > self.limit:  # what the browser said was its size is not what came
            self.refuse(name, len(value))
            return
        if (name, value) == (self.filename, self.value):
            self.param.trigger("value")  # the same file again: read again
        else:
            self.param.update(filename=name, value=value)
