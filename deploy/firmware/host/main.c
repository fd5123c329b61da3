/*
 * clothd-fw-host: the firmware core on a pseudo-terminal, for testing clothd's stepper link against the
 * C firmware without a board.
 *
 *   clothd-fw-host --link /tmp/x/ttyFW [--modules 48] [--exit-on-stdin-eof]
 *
 * Exits 0 on SIGTERM or SIGINT, and when stdin closes if --exit-on-stdin-eof (so a test that dies
 * takes the firmware with it). SIGUSR1 opens the hardware e-stop chain (the input a board reads from its
 * safety relay, docs/hardware.md) and SIGUSR2 closes it again: `kill -USR1 PID` is pressing the button.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <getopt.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "firmware.h"
#include "hal.h"
#include "hal_host.h"
#include "pty_link.h"

/* The loop wakes at least this often to run the watchdog and the ramps when no byte arrives. */
#define LOOP_POLL_TIMEOUT_MS 2

static volatile sig_atomic_t stop_requested;

static void on_stop_signal(int signo)
{
    (void)signo;
    stop_requested = 1;
}

typedef struct {
    const char *link_path;
    long n_modules;
    int exit_on_stdin_eof;
} host_options;

static void usage(FILE *out)
{
    fprintf(out, "usage: clothd-fw-host --link PATH [--modules N (1..%d, default 48)] "
                 "[--exit-on-stdin-eof]\n",
            FW_MAX_MODULES);
}

static int parse_options(int argc, char **argv, host_options *opt)
{
    static const struct option longopts[] = {
        {"link", required_argument, NULL, 'l'},
        {"modules", required_argument, NULL, 'm'},
        {"exit-on-stdin-eof", no_argument, NULL, 'e'},
        {"help", no_argument, NULL, 'h'},
        {NULL, 0, NULL, 0},
    };
    opt->link_path = NULL;
    opt->n_modules = 48;
    opt->exit_on_stdin_eof = 0;
    int c;
    while ((c = getopt_long(argc, argv, "", longopts, NULL)) != -1) {
        char *end = NULL;
        switch (c) {
        case 'l':
            opt->link_path = optarg;
            break;
        case 'm':
            opt->n_modules = strtol(optarg, &end, 10);
            if (*optarg == '\0' || *end != '\0' || opt->n_modules < 1 || opt->n_modules > FW_MAX_MODULES) {
                fprintf(stderr, "clothd-fw-host: --modules %s: not in 1..%d\n", optarg, FW_MAX_MODULES);
                return -1;
            }
            break;
        case 'e':
            opt->exit_on_stdin_eof = 1;
            break;
        case 'h':
            usage(stdout);
            exit(0);
        default:
            usage(stderr);
            return -1;
        }
    }
    if (opt->link_path == NULL || optind != argc) {
        usage(stderr);
        return -1;
    }
    return 0;
}

static void on_estop_signal(int signo)
{
    hal_host_set_estop_input(signo == SIGUSR1);
}

static void install_signal_handlers(void)
{
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal; /* no SA_RESTART: poll() returns EINTR and the loop sees the flag */
    sigemptyset(&sa.sa_mask);
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    /* Likewise: the loop polls the input at once. Each e-stop handler blocks the other: with both
     * pending, Linux stacks a frame for each and runs the last one set up (SIGUSR2) first, so a chain
     * opened and closed at once would end open. Blocked, they run one by one, SIGUSR1 first. */
    sa.sa_handler = on_estop_signal;
    sigaddset(&sa.sa_mask, SIGUSR1);
    sigaddset(&sa.sa_mask, SIGUSR2);
    sigaction(SIGUSR1, &sa, NULL);
    sigaction(SIGUSR2, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
}

/* True when stdin has reached end-of-file (its writer closed it); drains whatever it sent. */
static int stdin_closed(void)
{
    char sink[256];
    ssize_t n = read(STDIN_FILENO, sink, sizeof sink);
    return n == 0 || (n < 0 && errno != EINTR && errno != EAGAIN);
}

static void run_loop(fw_state *fw, int serial_fd, int watch_stdin)
{
    struct pollfd fds[2] = {
        {.fd = serial_fd, .events = POLLIN},
        {.fd = watch_stdin ? STDIN_FILENO : -1, .events = POLLIN}, /* fd -1: poll ignores it */
    };
    while (!stop_requested) {
        int ready = poll(fds, 2, LOOP_POLL_TIMEOUT_MS);
        if (ready < 0 && errno != EINTR) {
            perror("clothd-fw-host: poll");
            return;
        }
        if (ready > 0 && (fds[1].revents & (POLLIN | POLLHUP | POLLERR)) && stdin_closed()) {
            return;
        }
        fw_poll(fw);
    }
}

static void print_summary(const fw_state *fw)
{
    const fw_counters *c = &fw->counters;
    fprintf(stderr,
            "clothd-fw-host: frames ok %u invalid %u, commands applied %u repeated %u, nacks %u, "
            "faults %u, watchdog trips %u, e-stop input trips %u, e-stop %s, drivers %s\n",
            (unsigned)c->frames_ok, (unsigned)c->frames_invalid, (unsigned)c->commands_applied,
            (unsigned)c->commands_repeated, (unsigned)c->nacks_sent, (unsigned)c->faults_sent,
            (unsigned)c->watchdog_trips, (unsigned)c->estop_input_trips, fw->estop_latched ? "latched" : "clear",
            hal_host_drivers_enabled() ? "enabled" : "disabled");
}

int main(int argc, char **argv)
{
    static fw_state fw; /* static: the state is several kilobytes, and a firmware allocates nothing */
    host_options opt;
    if (parse_options(argc, argv, &opt) != 0) {
        return 2;
    }
    install_signal_handlers();
    pty_link pty;
    if (pty_link_open(&pty, opt.link_path) != 0) {
        pty_link_close(&pty);
        return 1;
    }
    hal_host_init(pty.master_fd);
    fw_config config = fw_default_config((uint16_t)opt.n_modules);
    if (!fw_init(&fw, &config, hal_now_ms())) {
        fprintf(stderr, "clothd-fw-host: invalid configuration\n");
        pty_link_close(&pty);
        return 1;
    }
    printf("clothd-fw-host: %s (%s) on %s, %ld modules\n", FW_NAME, opt.link_path, pty.slave_path,
           opt.n_modules);
    fflush(stdout);
    run_loop(&fw, pty.master_fd, opt.exit_on_stdin_eof);
    print_summary(&fw);
    pty_link_close(&pty);
    return 0;
}
