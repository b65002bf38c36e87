"""One log line at a level named by a word, as the cores hand their lines out: ('info' |
'warn' | 'error', text)."""


def log_at(logger, level: str, text: str) -> None:
    # rclpy refuses one call site with changing severities: one call per level.
    if level == 'error':
        logger.error(text)
    elif level == 'warn':
        logger.warning(text)
    else:
        logger.info(text)
