"""Scene uploads (``POST /scenes``), on the API's side; importing the package imports nothing heavy.

- :mod:`app.uploads.form`: the multipart form, every file part spooled to disk as it streams in;
- :mod:`app.uploads.staging`: stage an upload on disk, have it validated, store it atomically (the steps, in
  order, are in its docstring);
- :mod:`app.uploads.rules`: the rules a file's name and size meet, and what the API process and the validation
  process hand each other (:class:`~app.uploads.rules.StagedUpload` in, ``ValidatedScene`` out, ``UploadError``);
- :mod:`app.uploads.sandbox`: the validation in a child process under a memory and a time limit;
- :mod:`app.uploads.validation`: what that child does (unpack, check, import), the only one that loads torch.
"""
