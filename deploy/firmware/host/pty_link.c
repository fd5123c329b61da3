#define _DEFAULT_SOURCE /* cfmakeraw */
#define _XOPEN_SOURCE 700

#include "pty_link.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

static int fail(const char *what)
{
    int saved = errno;
    fprintf(stderr, "clothd-fw-host: %s: %s\n", what, strerror(saved));
    errno = saved;
    return -1;
}

/* A byte pipe like a USB CDC port: no echo, no line editing, no CR/LF translation. */
static int make_raw(int fd)
{
    struct termios tio;
    if (tcgetattr(fd, &tio) != 0) {
        return -1;
    }
    cfmakeraw(&tio);
    return tcsetattr(fd, TCSANOW, &tio);
}

static int open_master(pty_link *pty)
{
    pty->master_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (pty->master_fd < 0) {
        return fail("posix_openpt");
    }
    if (grantpt(pty->master_fd) != 0 || unlockpt(pty->master_fd) != 0) {
        return fail("grantpt/unlockpt");
    }
    const char *slave = ptsname(pty->master_fd); /* single-threaded: the static buffer is ours */
    if (slave == NULL || snprintf(pty->slave_path, sizeof pty->slave_path, "%s", slave) >=
                             (int)sizeof pty->slave_path) {
        return fail("ptsname");
    }
    /* Non-blocking: a host that does not read must not stall the firmware loop (writes then drop). */
    int flags = fcntl(pty->master_fd, F_GETFL);
    if (flags < 0 || fcntl(pty->master_fd, F_SETFL, flags | O_NONBLOCK) != 0) {
        return fail("fcntl O_NONBLOCK");
    }
    return 0;
}

/* Point link_path at the slave atomically: write link_path.new, then rename it over link_path. */
static int point_link(const pty_link *pty)
{
    char tmp[PATH_MAX];
    if (snprintf(tmp, sizeof tmp, "%s.new", pty->link_path) >= (int)sizeof tmp) {
        errno = ENAMETOOLONG;
        return fail("--link path");
    }
    if (unlink(tmp) != 0 && errno != ENOENT) {
        return fail(tmp);
    }
    if (symlink(pty->slave_path, tmp) != 0) {
        return fail(pty->link_path); /* its folder missing, most likely: name the path given */
    }
    if (rename(tmp, pty->link_path) != 0) {
        return fail(pty->link_path);
    }
    return 0;
}

int pty_link_open(pty_link *pty, const char *link_path)
{
    pty->master_fd = -1;
    pty->slave_fd = -1;
    pty->link_path = link_path;
    if (open_master(pty) != 0) {
        return -1;
    }
    pty->slave_fd = open(pty->slave_path, O_RDWR | O_NOCTTY);
    if (pty->slave_fd < 0) {
        return fail(pty->slave_path);
    }
    if (make_raw(pty->slave_fd) != 0) {
        return fail("raw mode");
    }
    return point_link(pty);
}

void pty_link_close(pty_link *pty)
{
    char target[sizeof pty->slave_path];
    ssize_t n = readlink(pty->link_path, target, sizeof target - 1);
    if (n >= 0) {
        target[n] = '\0';
        if (strcmp(target, pty->slave_path) == 0) {
            unlink(pty->link_path); /* only our own: someone may have re-pointed it since */
        }
    }
    if (pty->slave_fd >= 0) {
        close(pty->slave_fd);
    }
    if (pty->master_fd >= 0) {
        close(pty->master_fd);
    }
    pty->master_fd = pty->slave_fd = -1;
}
