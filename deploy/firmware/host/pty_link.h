/* The host build's serial line: a pseudo-terminal whose slave end is reachable by a stable symlink, as a
 * real controller would be by /dev/serial/by-id/... */
#ifndef CLOTHD_FW_PTY_LINK_H
#define CLOTHD_FW_PTY_LINK_H

typedef struct {
    int master_fd;
    int slave_fd; /* held open so the master never sees a hang-up while the host reconnects */
    char slave_path[128];
    const char *link_path;
} pty_link;

/* Open a raw pty and point link_path at its slave (replacing whatever was there). 0, or -1 with errno
 * set and a message on stderr. */
int pty_link_open(pty_link *pty, const char *link_path);

/* Remove the symlink (if it still points at this pty) and close both ends. */
void pty_link_close(pty_link *pty);

#endif
