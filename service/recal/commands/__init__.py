"""The batch commands: replay, hindsight, discover, import, export, static, demo."""
